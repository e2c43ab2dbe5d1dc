"""Static checks of the whole workspace, run by the test command like every other test.

ruff lints every Python file (rules and exclusions in pyproject.toml); mypy checks the pure
algorithm modules strictly (the Liberty codec, registration, occupancy, dwell, rotations,
object frame, map files; the list is in pyproject.toml's [tool.mypy] files).
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from conftest import WORKSPACE

TOOLS = Path(sys.executable).parent


def run(*command: str) -> subprocess.CompletedProcess:
    return subprocess.run(command, cwd=WORKSPACE, capture_output=True, text=True, timeout=600)


def test_ruff_finds_nothing_in_the_workspace():
    result = run(str(TOOLS / 'ruff'), 'check', '--no-cache', '.')
    assert result.returncode == 0, result.stdout + result.stderr


def test_mypy_strict_passes_on_the_pure_cores():
    result = run(str(TOOLS / 'mypy'), '--no-incremental')
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.startswith('Success'), result.stdout


def test_mypy_checks_the_cores_the_docs_name():
    """The list in pyproject.toml is the one the docs promise (docs/testing.md, "Static
    checks"): a file dropped from it would leave its module unchecked without a word."""
    import tomllib
    files = tomllib.loads((WORKSPACE / 'pyproject.toml').read_text())['tool']['mypy']['files']
    names = {Path(f).name for f in files}
    assert {'protocol.py', 'registration.py', 'occupancy.py', 'dwell.py', 'rotations.py',
            'object_frame.py', 'map_io.py'} <= names
    for name in files:
        assert (WORKSPACE / name).is_file(), name
    testing = (WORKSPACE / 'docs' / 'testing.md').read_text(encoding='utf-8')
    promised = re.search(r'^\.venv/bin/mypy +# --strict on (.+)$', testing, re.M)
    assert promised, 'docs/testing.md no longer says which modules mypy checks'
    for module in promised.group(1).split(','):
        assert f'{module.strip()}.py' in names, f'docs/testing.md promises {module.strip()}'


# Which workspace packages each package may import: none imports one above it.
ALLOWED_IMPORTS = {
    'inhand_common': set(),
    'polhemus_liberty': {'inhand_common'},
    'inhand_shape': {'inhand_common'},
    'inhand_mapping': {'inhand_common', 'inhand_shape'},
    'inhand_stereo': {'inhand_common', 'inhand_mapping', 'inhand_shape'},
    'inhand_sim': {'inhand_common', 'inhand_mapping', 'inhand_stereo', 'inhand_shape'},
    'inhand_tools': {'inhand_common', 'inhand_mapping', 'inhand_stereo', 'inhand_shape'},
    'inhand_view': {'inhand_common', 'inhand_mapping', 'inhand_tools', 'inhand_shape'},
}


def imported_modules(path: Path) -> set[str]:
    import ast
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def test_packages_are_layered_and_libraries_import_no_entry_point():
    problems = []
    for package, allowed in ALLOWED_IMPORTS.items():
        for path in sorted((WORKSPACE / 'src' / package / package).rglob('*.py')):
            is_entry_point = path.parent.name in ('nodes', 'commands')
            for module in imported_modules(path):
                top = module.split('.')[0]
                where = path.relative_to(WORKSPACE)
                if top in ALLOWED_IMPORTS and top != package and top not in allowed:
                    problems.append(f'{where} imports {module}: {package} may import '
                                    f'{sorted(allowed) or "no workspace package"}')
                parts = module.split('.')
                if not is_entry_point and top in ALLOWED_IMPORTS and \
                        ('nodes' in parts[1:] or 'commands' in parts[1:]):
                    problems.append(f'{where} (a library module) imports the entry point '
                                    f'{module}')
    assert not problems, '\n'.join(problems)


MAX_FUNCTION_LINES = 100


def test_no_function_is_longer_than_a_hundred_lines():
    """A function that does not fit on a screen and a half does more than one thing."""
    import ast
    long = []
    for path in sorted((WORKSPACE / 'src').rglob('*.py')):
        for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1
                if lines > MAX_FUNCTION_LINES:
                    long.append(f'{path.relative_to(WORKSPACE)}:{node.lineno} {node.name} '
                                f'({lines} lines)')
    assert not long, long
