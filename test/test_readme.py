"""The README stays true to the code: its commands exist and its tables match the specs."""

import re

import pytest

from conftest import WORKSPACE
from inhand_mapping.mapping_config import OCCUPANCY_PARAMETERS, REGISTRATION_PARAMETERS
from inhand_stereo.stereo_config import STEREO_PARAMETERS
from inhand_view.view_config import VIEW_PARAMETERS
from polhemus_liberty.driver_config import DRIVER_PARAMETERS

README = (WORKSPACE / 'README.md').read_text(encoding='utf-8')


def test_ci_runs_the_readme_test_command():
    ci = (WORKSPACE / '.ci' / 'run').read_text(encoding='utf-8')
    assert 'bash launch_scripts/run_tests.sh' in README
    assert 'bash launch_scripts/run_tests.sh' in ci


def test_scripts_named_in_the_readme_exist():
    for script in set(re.findall(r'launch_scripts/[\w.]+\.sh', README)):
        assert (WORKSPACE / script).is_file(), f'README names {script}, which does not exist'


@pytest.mark.parametrize('specs', [DRIVER_PARAMETERS, REGISTRATION_PARAMETERS,
                                   OCCUPANCY_PARAMETERS, STEREO_PARAMETERS, VIEW_PARAMETERS],
                         ids=['driver', 'registration', 'occupancy', 'stereo', 'view'])
def test_every_node_parameter_is_documented_with_its_allowed_values(specs):
    rows = {m.group(1): m.group(0) for m in re.finditer(r'^\| `(\w+)` \|.*$', README, re.M)}
    for spec in specs:
        assert spec.name in rows, f'parameter {spec.name} missing from the README table'
        assert f'| {spec.allowed()} |' in rows[spec.name], f'{spec.name}: allowed values differ'
        assert spec.description in rows[spec.name], f'{spec.name}: description differs'
