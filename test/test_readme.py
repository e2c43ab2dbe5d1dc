"""The README and the manual stay true to the code: their commands exist and answer, their
links resolve, the README stays one page, and the parameter tables match the specs.

What is checked is the README (the front page), docs/*.md (the manual) and every
src/<package>/README.md, together.
"""

import ast
import os
import re
import signal
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from conftest import WORKSPACE
from inhand_mapping.mapping_config import OCCUPANCY_PARAMETERS, REGISTRATION_PARAMETERS
from inhand_shape.shape_extraction import SHAPE_PARAMETERS
from inhand_shape.touch_guidance import EXPLORATION_NODE_PARAMETERS
from inhand_stereo.stereo_config import STEREO_PARAMETERS
from inhand_view.view_config import VIEW_PARAMETERS
from polhemus_liberty.driver_config import DRIVER_PARAMETERS

README_PATH = WORKSPACE / 'README.md'
DOCS = sorted((WORKSPACE / 'docs').glob('*.md'))
PACKAGE_READMES = sorted((WORKSPACE / 'src').glob('*/README.md'))
PAGES = [README_PATH, *DOCS, *PACKAGE_READMES]
TEXTS = {path: path.read_text(encoding='utf-8') for path in PAGES}
README = TEXTS[README_PATH]
ALL_TEXT = '\n'.join(TEXTS.values())

VENV_BIN = Path(sys.executable).parent
MAX_README_LINES = 250


def relative(path: Path) -> str:
    return str(path.relative_to(WORKSPACE))


def without_code_blocks(text: str) -> str:
    """The text outside fenced code blocks (their lines blanked, so line numbers hold)."""
    lines, fenced = [], False
    for line in text.split('\n'):
        if line.lstrip().startswith('```'):
            fenced = not fenced
            lines.append('')
        else:
            lines.append('' if fenced else line)
    return '\n'.join(lines)


def code_blocks(text: str, language: str) -> list[str]:
    return re.findall(rf'^```{language}\n(.*?)^```', text, re.M | re.S)


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lowercase, punctuation but hyphens (and the underscores
    of words) dropped, spaces to hyphens."""
    text = re.sub(r'[^\w\- ]', '', heading.strip().lower())
    return text.replace(' ', '-')


def anchors(text: str) -> set[str]:
    found: set[str] = set()
    counts: dict[str, int] = {}
    for match in re.finditer(r'^#{1,6} +(.+?) *#* *$', without_code_blocks(text), re.M):
        base = slug(match.group(1))
        count = counts.get(base, 0)
        counts[base] = count + 1
        found.add(base if count == 0 else f'{base}-{count}')
    return found


LINK = re.compile(r'!?\[[^\]\n]*\]\(([^)\s]+)\)')


def links(text: str) -> list[str]:
    prose = without_code_blocks(text)
    # link texts may hold inline code; code spans elsewhere may hold brackets: blank them
    prose = re.sub(r'`[^`\n]*`', '``', prose)
    return LINK.findall(prose)


def test_ci_runs_the_readme_test_command():
    ci = (WORKSPACE / '.ci' / 'run').read_text(encoding='utf-8')
    assert 'bash launch_scripts/run_tests.sh' in README
    assert 'bash launch_scripts/run_tests.sh' in ci


def test_the_two_commands_are_on_the_front_page():
    section = README.split('## Two commands', 1)[1].split('\n## ', 1)[0]
    block = code_blocks(section, 'bash')[0]
    assert block.startswith('bash launch_scripts/demo.sh ')
    assert '\nbash launch_scripts/run_tests.sh ' in block


def test_the_readme_is_one_page():
    lines = README.count('\n') + (not README.endswith('\n'))
    assert lines <= MAX_README_LINES, f'README.md has {lines} lines: the manual belongs in docs/'


def test_every_docs_page_is_linked_from_the_readme():
    targets = {os.path.normpath(target.split('#')[0]) for target in links(README)}
    missing = [relative(page) for page in DOCS if relative(page) not in targets]
    assert not missing, f'README.md links no page of {missing}'


def test_every_package_has_a_readme_that_points_to_the_docs():
    for package in sorted(p for p in (WORKSPACE / 'src').iterdir() if (p / 'setup.py').is_file()):
        readme = package / 'README.md'
        assert readme.is_file(), f'{relative(package)} has no README.md'
        assert any(t.split('#')[0].startswith('../../docs/') for t in links(TEXTS[readme])), \
            f'{relative(readme)} links no docs page'


def test_every_relative_link_resolves():
    problems = []
    for page, text in TEXTS.items():
        for target in links(text):
            if re.match(r'[a-z][a-z0-9+.-]*:', target):     # http:, https:, mailto:
                continue
            path_part, _, anchor = target.partition('#')
            destination = (page.parent / path_part).resolve() if path_part else page
            if not destination.exists():
                problems.append(f'{relative(page)}: {target}: no such file')
                continue
            if anchor and destination.suffix == '.md':
                if anchor not in anchors(destination.read_text(encoding='utf-8')):
                    problems.append(f'{relative(page)}: {target}: no heading #{anchor} there')
    assert not problems, '\n'.join(problems)


def test_scripts_named_in_the_docs_exist():
    for script in set(re.findall(r'launch_scripts/[\w.]+\.sh', ALL_TEXT)):
        assert (WORKSPACE / script).is_file(), f'the docs name {script}, which does not exist'


def console_scripts() -> dict[str, str]:
    """Every console script of the workspace: name -> 'module:function'."""
    scripts = {}
    for setup in sorted((WORKSPACE / 'src').glob('*/setup.py')):
        for node in ast.walk(ast.parse(setup.read_text(encoding='utf-8'))):
            if isinstance(node, ast.keyword) and node.arg == 'entry_points':
                entry_points = ast.literal_eval(node.value)
                for line in entry_points.get('console_scripts', []):
                    name, _, target = (part.strip() for part in line.partition('='))
                    scripts[name] = target
    return scripts


def quoted_commands(scripts: dict[str, str]) -> set[str]:
    """The console scripts the docs run: at the start of a line of a bash block (bare or
    as .venv/bin/NAME), or after `ros2 run <package> `."""
    quoted = set()
    for text in TEXTS.values():
        for block in code_blocks(text, 'bash'):
            for line in block.split('\n'):
                match = re.match(r'\s*(?:sudo\s+)?(?:\.venv/bin/)?([\w-]+)', line)
                if match and match.group(1) in scripts:
                    quoted.add(match.group(1))
        quoted.update(name for name in re.findall(r'ros2 run \w+ (\w+)', text) if name in scripts)
    return quoted


def run(command: list[str]) -> tuple[list[str], int | None, str]:
    """Exit code (None: still running after the timeout, stopped with its children) and
    output of one command."""
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    process = subprocess.Popen(command, cwd=WORKSPACE, env=env, text=True,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                               start_new_session=True)
    try:
        output, _ = process.communicate(timeout=120)
        return command, process.returncode, output
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        output, _ = process.communicate()
        return command, None, output


def run_all(commands: list[list[str]]) -> list[str]:
    """Runs the commands side by side; the failures, each with its output's tail."""
    with ThreadPoolExecutor(max_workers=8) as pool:
        results = list(pool.map(run, commands))
    return [f'{" ".join(command)}: ' + ('no answer in 120 s' if code is None else f'exit {code}')
            + f'\n{output[-600:]}' for command, code, output in results if code != 0]


def test_every_command_the_docs_quote_answers():
    """Commands answer --help with exit code 0. A ROS node takes --ros-args, not --help (it
    would start and run), so for a node the check is that its entry point imports."""
    scripts = console_scripts()
    quoted = quoted_commands(scripts)
    assert {'build_map', 'liberty_driver', 'simulate_session', 'stereo_node'} <= quoted
    commands = []
    for name in sorted(quoted):
        module, _, function = scripts[name].partition(':')
        if '.nodes.' in module:
            commands.append([sys.executable, '-c',
                             f'import {module} as m; assert callable(m.{function})'])
        else:
            commands.append([str(VENV_BIN / name), '--help'])
    failures = run_all(commands)
    assert not failures, '\n'.join(failures)


def answers_help(script: Path) -> bool:
    """A launch script takes --help when it says so, or when it hands its arguments to a
    launch file of its own that parses them with argparse."""
    text = script.read_text(encoding='utf-8')
    if re.search(r'^\s*[^#\n]*--help\)', text, re.M):     # a case branch
        return True
    for target in re.findall(r'launch_scripts/(\w+\.py)"? "\$@"', text):
        launch_file = script.parent / target
        if launch_file.is_file() and 'argparse' in launch_file.read_text(encoding='utf-8'):
            return True
    return False


def test_launch_scripts_the_docs_name_exist_and_answer_help():
    named = sorted(set(re.findall(r'launch_scripts/[\w.]+\.sh', ALL_TEXT)))
    assert 'launch_scripts/demo.sh' in named
    helpful = [WORKSPACE / script for script in named if answers_help(WORKSPACE / script)]
    assert WORKSPACE / 'launch_scripts/demo.sh' in helpful
    failures = run_all([['bash', str(script), '--help'] for script in helpful])
    assert not failures, '\n'.join(failures)


@pytest.mark.parametrize('specs', [DRIVER_PARAMETERS, REGISTRATION_PARAMETERS,
                                   OCCUPANCY_PARAMETERS, STEREO_PARAMETERS, VIEW_PARAMETERS,
                                   SHAPE_PARAMETERS, EXPLORATION_NODE_PARAMETERS],
                         ids=['driver', 'registration', 'occupancy', 'stereo', 'view', 'shape',
                              'exploration'])
def test_every_node_parameter_is_documented_with_its_allowed_values(specs):
    rows: dict[str, list[str]] = {}
    for match in re.finditer(r'^\| `(\w+)` \|.*$', ALL_TEXT, re.M):
        rows.setdefault(match.group(1), []).append(match.group(0))
    for spec in specs:
        assert spec.name in rows, f'parameter {spec.name} missing from the docs tables'
        assert any(f'| {spec.allowed()} |' in row for row in rows[spec.name]), \
            f'{spec.name}: allowed values differ'
        assert any(f'| {spec.allowed()} |' in row and spec.description in row
                   for row in rows[spec.name]), f'{spec.name}: description differs'
