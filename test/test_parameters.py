"""ParamSpec / validate / load_yaml_parameters (no ROS needed)."""

import math

import pytest

from inhand_common.parameters import (
    ParameterError,
    ParamSpec,
    load_yaml_parameters,
    read_parameter_file,
    validate,
)

SPECS = [
    ParamSpec('port', '/dev/ttyUSB0', 'serial device'),
    ParamSpec('baud', 115200, 'serial speed', choices=(9600, 19200, 38400, 57600, 115200)),
    ParamSpec('rate_hz', 240, 'frame rate', choices=(120, 240)),
    ParamSpec('stations', 4, 'number of sensors', minimum=1, maximum=16),
    ParamSpec('latency_s', 0.004, 'stamp correction', minimum=0.0, maximum=0.1),
    ParamSpec('units', 'cm', 'device units', choices=('cm', 'inch')),
    ParamSpec('binary', True, 'F1 output'),
    ParamSpec('hemisphere', [1.0, 0.0, 0.0], 'H* vector', minimum=-1.0, maximum=1.0, length=3),
    ParamSpec('items', [8, 9, 2, 7, 1], 'output list', minimum=0, maximum=12, min_length=1),
]


def refused(values, specs=SPECS):
    with pytest.raises(ParameterError) as info:
        validate(specs, values)
    return info.value


def test_defaults_pass_and_come_back():
    result = validate(SPECS, {})
    assert result == {s.name: (list(s.default) if s.is_list else s.default) for s in SPECS}
    assert isinstance(result['hemisphere'], list)


def test_given_values_override_defaults():
    result = validate(SPECS, {'stations': 8, 'units': 'inch', 'binary': False})
    assert result['stations'] == 8
    assert result['units'] == 'inch'
    assert result['binary'] is False
    assert result['rate_hz'] == 240


def test_out_of_range_message_names_parameter_value_and_range():
    error = refused({'stations': 17})
    assert len(error.problems) == 1
    message = error.problems[0]
    assert "'stations'" in message
    assert '17' in message
    assert '[1, 16]' in message
    assert 'stations' in str(error) and '17' in str(error)


def test_range_in_message_is_not_rounded():
    # A bound with more than six significant digits must appear as it is, or the message
    # names a range that is not the one enforced.
    spec = ParamSpec('buffer_bytes', 4096, 'read buffer', minimum=1, maximum=1048576)
    with pytest.raises(ParameterError) as info:
        validate([spec], {'buffer_bytes': 1048577})
    message = info.value.problems[0]
    assert '1048577' in message
    assert '[1, 1048576]' in message


def test_float_out_of_range_message():
    error = refused({'latency_s': 0.5})
    message = error.problems[0]
    assert "'latency_s'" in message and '0.5' in message and '[0, 0.1]' in message


@pytest.mark.parametrize('value', [0, -3, 17, 1000])
def test_int_bounds_are_inclusive_and_enforced(value):
    refused({'stations': value})


@pytest.mark.parametrize('value', [1, 16])
def test_int_bounds_inclusive(value):
    assert validate(SPECS, {'stations': value})['stations'] == value


@pytest.mark.parametrize('name, value', [
    ('stations', True),        # bool is not an int here
    ('stations', False),
    ('stations', 4.0),         # float for int
    ('stations', '4'),
    ('latency_s', '0.01'),     # string for float
    ('latency_s', True),
    ('latency_s', None),
    ('binary', 1),             # int for bool
    ('binary', 'true'),
    ('port', 0),
    ('units', 1),
])
def test_wrong_types_are_refused(name, value):
    error = refused({name: value})
    assert len(error.problems) == 1
    assert f"'{name}'" in error.problems[0]
    assert repr(value) in error.problems[0]


def test_int_accepted_for_float_and_coerced():
    result = validate(SPECS, {'latency_s': 0})
    assert result['latency_s'] == 0.0
    assert type(result['latency_s']) is float
    result = validate(SPECS, {'hemisphere': [0, 0, -1]})
    assert result['hemisphere'] == [0.0, 0.0, -1.0]
    assert all(type(v) is float for v in result['hemisphere'])


@pytest.mark.parametrize('value', [math.nan, math.inf, -math.inf])
def test_non_finite_float_refused(value):
    error = refused({'latency_s': value})
    assert "'latency_s'" in error.problems[0]


def test_nan_refused_even_without_bounds():
    spec = ParamSpec('gain', 1.0, 'unbounded')
    with pytest.raises(ParameterError):
        validate([spec], {'gain': math.nan})
    assert validate([spec], {'gain': -1e300}) == {'gain': -1e300}


@pytest.mark.parametrize('value', [
    [1.0, 0.0],                # too short
    [1.0, 0.0, 0.0, 0.0],      # too long
    [2.0, 0.0, 0.0],           # element out of range
    [0.0, math.nan, 0.0],      # element not finite
    [0.0, '0', 0.0],           # element of the wrong type
    [0.0, True, 0.0],
    1.0,                       # not a list
    'x',
])
def test_bad_lists_refused(value):
    error = refused({'hemisphere': value})
    assert "'hemisphere'" in error.problems[0]
    assert 'exactly 3' in error.problems[0]


def test_list_min_length_and_element_range():
    assert validate(SPECS, {'items': [2, 4, 1]})['items'] == [2, 4, 1]
    assert validate(SPECS, {'items': (2, 7)})['items'] == [2, 7]
    refused({'items': []})
    refused({'items': [2, 13]})
    refused({'items': [2, -1]})
    refused({'items': [2.0, 4.0]})


def test_choices():
    assert validate(SPECS, {'rate_hz': 120})['rate_hz'] == 120
    error = refused({'rate_hz': 60})
    assert "'rate_hz'" in error.problems[0] and '60' in error.problems[0]
    assert '120' in error.problems[0] and '240' in error.problems[0]
    error = refused({'units': 'mm'})
    assert "'mm'" in error.problems[0] and "'cm'" in error.problems[0]


def test_unknown_names_reported():
    error = refused({'stationz': 4})
    assert len(error.problems) == 1
    assert "'stationz'" in error.problems[0]
    assert 'stations' in error.problems[0]  # the known names are listed


def test_a_typo_is_refused_with_the_closest_valid_name():
    error = refused({'stationz': 4, 'zzz': 1})
    assert "unknown parameter 'stationz' (did you mean 'stations'?)" in error.problems
    assert any("'zzz' (known: " in problem for problem in error.problems)


def test_an_empty_list_is_shown_as_typed():
    # -p name:=[] reaches a node as no value at all
    for value in (None, []):
        error = refused({'hemisphere': value})
        assert "'hemisphere' = [] is refused" in error.problems[0]


def test_unreadable_and_malformed_parameter_files_are_one_line(tmp_path):
    missing = tmp_path / 'missing.yaml'
    with pytest.raises(ParameterError) as caught:
        read_parameter_file(str(missing))
    assert caught.value.problems == [f'{missing}: cannot read the parameter file '
                                     '(No such file or directory)']
    bad = tmp_path / 'bad.yaml'
    bad.write_text('node:\n  ros__parameters:\n    mode: [static\n', encoding='utf-8')
    with pytest.raises(ParameterError) as caught:
        load_yaml_parameters(str(bad), 'node')
    assert len(caught.value.problems) == 1
    assert caught.value.problems[0].startswith(f'{bad}: not valid YAML at line 4')


@pytest.mark.parametrize('arguments, message', [
    (['--params-file', 'MISSING'], 'MISSING: cannot read the parameter file'),
    (['--params-file', 'BAD'], 'BAD: not valid YAML at line'),
    (['-p', 'finger_nams:=[a]'], "unknown parameter 'finger_nams' (did you mean 'finger_names'?)"),
    (['-p', 'finger_names:=[]'], "'finger_names' = [] is refused"),
], ids=['missing-file', 'bad-yaml', 'typo', 'empty-list'])
def test_a_node_refuses_bad_parameters_in_a_line_without_a_traceback(tmp_path, arguments,
                                                                     message):
    import subprocess

    from ros_helpers import executable_path
    bad = tmp_path / 'bad.yaml'
    bad.write_text('registration_node:\n  ros__parameters:\n    mode: [static\n')
    paths = {'MISSING': str(tmp_path / 'missing.yaml'), 'BAD': str(bad)}
    arguments = [paths.get(a, a) for a in arguments]
    message = message.replace('MISSING', paths['MISSING']).replace('BAD', paths['BAD'])
    result = subprocess.run([executable_path('registration_node'), '--ros-args', *arguments],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2, result.stderr
    assert message in result.stderr and 'Traceback' not in result.stderr


def test_several_problems_reported_together():
    error = refused({'stations': 0, 'latency_s': 'fast', 'bogus': 1, 'units': 'mm',
                     'hemisphere': [1.0]})
    assert len(error.problems) == 5
    text = str(error)
    for name in ('stations', 'latency_s', 'bogus', 'units', 'hemisphere'):
        assert name in text


def test_allowed_phrases():
    assert SPECS[3].allowed() == 'an integer in [1, 16]'
    assert ParamSpec('a', 1.0, '', minimum=0.0).allowed() == 'a number >= 0'
    assert ParamSpec('a', 1, '', maximum=5).allowed() == 'an integer <= 5'
    assert ParamSpec('a', 'x', '').allowed() == 'a string'
    assert ParamSpec('a', False, '').allowed() == 'true or false'
    assert SPECS[7].allowed() == 'a list of exactly 3 elements, each a number in [-1, 1]'


def test_empty_list_default_is_a_spec_error():
    # Refused where the table is written, not later when a value arrives.
    with pytest.raises(TypeError, match='empty'):
        ParamSpec('empty', [], 'no element type')


# ----------------------------------------------------------------------------- YAML

def test_load_yaml_node_section(tmp_path):
    path = tmp_path / 'liberty.yaml'
    path.write_text(
        'liberty_driver:\n'
        '  ros__parameters:\n'
        '    port: /dev/ttyUSB1\n'
        '    stations: 2\n'
        '    hemisphere: [0.0, 0.0, 1.0]\n'
        'other_node:\n'
        '  ros__parameters:\n'
        '    stations: 9\n', encoding='utf-8')
    values = load_yaml_parameters(str(path), 'liberty_driver')
    assert values == {'port': '/dev/ttyUSB1', 'stations': 2, 'hemisphere': [0.0, 0.0, 1.0]}
    result = validate(SPECS, values)
    assert result['stations'] == 2 and result['port'] == '/dev/ttyUSB1'
    assert load_yaml_parameters(str(path), 'other_node') == {'stations': 9}
    assert load_yaml_parameters(str(path), 'absent') == {}


def test_load_yaml_wildcard_then_node_overrides(tmp_path):
    path = tmp_path / 'params.yaml'
    path.write_text(
        '/**:\n'
        '  ros__parameters:\n'
        '    units: inch\n'
        '    stations: 3\n'
        '/liberty_driver:\n'
        '  ros__parameters:\n'
        '    stations: 5\n', encoding='utf-8')
    assert load_yaml_parameters(str(path), 'liberty_driver') == {'units': 'inch', 'stations': 5}
    assert load_yaml_parameters(str(path), 'someone_else') == {'units': 'inch', 'stations': 3}


def test_load_yaml_node_in_any_namespace(tmp_path):
    """``/**/node:`` (what calibrate_camera_tracker writes) applies to the node in any
    namespace, as rcl reads it; the node's own section still overrides it."""
    path = tmp_path / 'params.yaml'
    path.write_text(
        '/**/stereo_node:\n'
        '  ros__parameters:\n'
        '    point_step: 3\n'
        '    resolution: 0.004\n'
        'stereo_node:\n'
        '  ros__parameters:\n'
        '    point_step: 1\n', encoding='utf-8')
    assert load_yaml_parameters(str(path), 'stereo_node') == {'point_step': 1,
                                                               'resolution': 0.004}
    assert load_yaml_parameters(str(path), 'occupancy_node') == {}


def test_load_yaml_empty_and_bad_files(tmp_path):
    empty = tmp_path / 'empty.yaml'
    empty.write_text('', encoding='utf-8')
    assert load_yaml_parameters(str(empty), 'n') == {}
    not_mapping = tmp_path / 'list.yaml'
    not_mapping.write_text('- 1\n- 2\n', encoding='utf-8')
    with pytest.raises(ParameterError):
        load_yaml_parameters(str(not_mapping), 'n')


def test_yaml_values_are_validated_with_all_problems(tmp_path):
    path = tmp_path / 'bad.yaml'
    path.write_text(
        'liberty_driver:\n'
        '  ros__parameters:\n'
        '    stations: 40\n'
        '    rate_hz: 60\n'
        '    typo_name: 1\n', encoding='utf-8')
    error = refused(load_yaml_parameters(str(path), 'liberty_driver'))
    assert len(error.problems) == 3


# ------------------------------------------------------------------ on a real rclpy node

@pytest.fixture
def ros_context():
    import rclpy
    context = rclpy.Context()
    rclpy.init(context=context)
    yield context
    rclpy.try_shutdown(context=context)


def make_node(context, *arguments):
    from rclpy.node import Node
    return Node('parameter_test', context=context, cli_args=['--ros-args', *arguments])


def test_command_line_overrides_reach_declare_parameters(ros_context):
    """Pins the rclpy behaviour ros_parameters relies on (values given with -p are readable
    before they are declared): an rclpy upgrade that moves them fails here, loudly."""
    from inhand_common.ros_parameters import command_line_overrides, declare_parameters
    node = make_node(ros_context, '-p', 'latency_s:=0', '-p', 'units:=inch',
                     '-p', 'stations:=3')
    try:
        given = command_line_overrides(node)
        assert {name: given[name].value for name in ('latency_s', 'units', 'stations')} == \
            {'latency_s': 0, 'units': 'inch', 'stations': 3}
        values = declare_parameters(node, SPECS)
        assert values['units'] == 'inch' and values['stations'] == 3
        # an integer given for a float parameter is coerced and declared as a float
        assert values['latency_s'] == 0.0 and isinstance(values['latency_s'], float)
        assert node.get_parameter('latency_s').value == 0.0
        assert node.get_parameter('port').value == '/dev/ttyUSB0'   # the default
        descriptor = node.describe_parameter('stations')
        assert (descriptor.integer_range[0].from_value, descriptor.integer_range[0].to_value) \
            == (1, 16)
    finally:
        node.destroy_node()


def test_declare_parameters_refuses_a_bad_value_with_its_range(ros_context):
    from inhand_common.ros_parameters import declare_parameters
    node = make_node(ros_context, '-p', 'stations:=40')
    try:
        with pytest.raises(ParameterError,
                           match=r"'stations' = 40 is refused: allowed is an integer in \[1, 16\]"):
            declare_parameters(node, SPECS)
    finally:
        node.destroy_node()


def test_a_grid_is_checked_against_the_memory_the_machine_has():
    from inhand_common.machine_memory import available_memory, human_bytes
    from inhand_mapping.mapping_config import BYTES_PER_CELL, memory_problem
    assert memory_problem(70, 'none', 10**9) is None                  # the default: 80 MB
    assert memory_problem(1000, 'none', None) is None                 # the machine does not say
    problem = memory_problem(1000, 'product', 24 * 2**30)
    assert '1000^3 cells, about 353.0 GB of memory; this machine has 24.0 GB available' in problem
    assert BYTES_PER_CELL['fusion'] > BYTES_PER_CELL['none']
    assert human_bytes(1536) == '1.5 KB' and human_bytes(12) == '12 B'
    available = available_memory()
    assert available is None or available > 0
