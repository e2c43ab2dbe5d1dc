"""topic_echo: its text (whole arrays, -l, --no-arr/--no-str, bulk data, CSV), its --filter
and its arguments without ROS, then the real executable against rclpy publishers over DDS:
a 21-key DiagnosticArray printed whole with --once, --csv, --filter (also on a --field
value, and one that fails), a type given before the topic exists, and a type that is not
the graph's.
"""

from __future__ import annotations

import contextlib
import subprocess
import threading
import time

import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseWithCovarianceStamped
from sensor_msgs.msg import Image, PointCloud2
from shape_msgs.msg import SolidPrimitive
from std_msgs.msg import Float32MultiArray, String

from inhand_tools.echo_format import (
    FilterError,
    Options,
    compile_filter,
    echo_text,
    format_csv,
    format_message,
)
from ros_helpers import BackgroundNode, executable_path, running

KEYS = 21


def diagnostics(k: int = 0, keys: int = KEYS, name: str = 'liberty: driver') -> DiagnosticArray:
    """One status with ``keys`` KeyValues; stamp.sec = k and value i = i * k."""
    msg = DiagnosticArray()
    msg.header.stamp.sec = k
    msg.header.frame_id = 'liberty'
    msg.status = [DiagnosticStatus(level=bytes([k % 3]), name=name, message='ok',
                                   hardware_id='tracker',
                                   values=[KeyValue(key=f'key{i}', value=str(i * k))
                                           for i in range(keys)])]
    return msg


# -- the YAML text -----------------------------------------------------------------------------

def test_arrays_and_strings_are_printed_whole_by_default():
    msg = diagnostics(3)
    msg.status[0].message = 'x' * 300
    document = yaml.safe_load(format_message(msg))
    values = document['status'][0]['values']
    assert len(values) == KEYS and '...' not in format_message(msg)
    assert values[-1] == {'key': 'key20', 'value': '60'}
    assert document['status'][0]['message'] == 'x' * 300
    pose = PoseWithCovarianceStamped()
    pose.pose.covariance[:] = np.arange(36) * 0.5
    assert yaml.safe_load(format_message(pose))['pose']['covariance'] == list(np.arange(36) * 0.5)


def test_truncate_length_cuts_arrays_and_strings_and_full_length_overrides_it():
    msg = diagnostics(2)
    text = format_message(msg, Options(truncate_length=4))
    status = yaml.safe_load(text)['status'][0]
    assert status['name'] == 'libe...'
    assert [v['key'] for v in status['values'][:4]] == ['key0', 'key1', 'key2', 'key3']
    assert status['values'][4] == '...' and len(status['values']) == 5
    assert f'- ...  # {KEYS} items' in text
    floats = Float32MultiArray(data=[0.1, 0.2, 0.3])
    assert 'data: [0.1, 0.2, ...]  # 3 items' in format_message(floats, Options(truncate_length=2))
    assert 'data: [...]  # 3 items' in format_message(floats, Options(truncate_length=0))
    whole = yaml.safe_load(format_message(msg, Options(truncate_length=4, full_length=True)))
    assert len(whole['status'][0]['values']) == KEYS
    assert whole['status'][0]['name'] == 'liberty: driver'


def test_no_arr_and_no_str_print_ros2s_summaries():
    msg = diagnostics(1)
    document = yaml.safe_load(format_message(msg, Options(no_arr=True, no_str=True)))
    assert document['status'] == \
        '<sequence type: diagnostic_msgs/msg/DiagnosticStatus, length: 1>'
    assert document['header']['frame_id'] == '<string length: <7>>'
    pose = PoseWithCovarianceStamped()
    assert yaml.safe_load(format_message(pose, Options(no_arr=True)))['pose']['covariance'] == \
        '<array type: double[36]>'
    box = SolidPrimitive(type=1, dimensions=[1.0, 2.0])
    assert yaml.safe_load(format_message(box, Options(no_arr=True)))['dimensions'] == \
        '<sequence type: double[3], length: 2>'
    strings = yaml.safe_load(format_message(msg, Options(no_str=True)))['status'][0]
    assert strings['name'] == '<string length: <15>>' and len(strings['values']) == KEYS


def test_image_bytes_stay_summarised_unless_full_length():
    image = Image(height=2, width=3, encoding='rgb8', step=9, data=bytes(range(18)))
    summary = yaml.safe_load(format_message(image))
    assert summary['data'] == '<18 bytes; --full-length shows them>'
    assert summary['encoding'] == 'rgb8' and summary['step'] == 9
    assert yaml.safe_load(format_message(image, Options(full_length=True)))['data'] == \
        list(range(18))
    assert format_csv(image) == '0,0,,2,3,rgb8,0,9,<18 bytes; --full-length shows them>'
    assert format_csv(image, Options(full_length=True)).endswith(
        ',9,' + ','.join(map(str, range(18))))
    cloud = PointCloud2(height=1, width=0, data=bytes(8))
    assert format_csv(cloud).endswith(',<8 bytes; --full-length shows them>,False')


# -- CSV -------------------------------------------------------------------------------------

def test_csv_flattens_nested_messages_and_arrays_in_field_order():
    msg = diagnostics(2, keys=2)
    msg.status.append(DiagnosticStatus(level=b'\x02', name='b', values=[]))
    # header (sec, nanosec, frame_id), then each status: level, name, message, hardware_id,
    # its values' key and value; the second status' empty values an empty last column.
    assert format_csv(msg) == \
        '2,0,liberty,2,liberty: driver,ok,tracker,key0,0,key1,2,2,b,,,'
    # -l 1: strings to one character, arrays to one item and '...'
    assert format_csv(msg, Options(truncate_length=1)) == \
        '2,0,l...,2,l...,o...,t...,k...,0,...,...'
    assert format_csv(msg, Options(no_arr=True)) == \
        '2,0,liberty,"<sequence type: diagnostic_msgs/msg/DiagnosticStatus, length: 2>"'
    assert format_csv(msg, Options(no_str=True)).startswith(
        '2,0,<string length: <7>>,2,<string length: <15>>,')


def test_csv_values_quote_commas_and_keep_float32_short():
    assert format_csv(String(data='a,b "c"')) == '"a,b ""c"""'
    assert format_csv(String(data='plain')) == 'plain'
    floats = Float32MultiArray(data=[0.1, 2.5])
    assert format_csv(floats) == ',0,0.1,2.5'  # layout: no dims (empty), data_offset 0
    assert format_csv(PointCloud2(is_dense=True)).endswith(',True')


def test_echo_text_says_which_values_are_lines_of_their_own():
    msg = diagnostics(1, keys=1)
    assert echo_text(msg, Options(csv=True)) == (format_csv(msg), True)
    text, single = echo_text(msg, Options())
    assert text == format_message(msg) and not single
    assert echo_text(3.5, Options(), 'float64') == ('3.5', True)
    assert echo_text('a long name', Options(truncate_length=3)) == ('a l...', True)
    assert echo_text(msg.status, Options(), 'sequence<diagnostic_msgs/msg/DiagnosticStatus>')[1] \
        is False


# -- the filter --------------------------------------------------------------------------------

def test_filter_is_true_false_and_sees_m_everywhere():
    msg = diagnostics(4)
    assert compile_filter('m.header.stamp.sec > 3')(msg) is True
    assert compile_filter('m.header.stamp.sec > 4')(msg) is False
    assert compile_filter('len(m.status[0].values) == 21')(msg) is True
    # m inside a comprehension (a nested scope) and a lambda
    assert compile_filter("any(kv.value == str(4 * 20) for kv in m.status[0].values)")(msg)
    assert not compile_filter("[kv for kv in m.status[0].values if kv.key == m.header.frame_id]")(msg)
    assert compile_filter('(lambda s: s.name.startswith("liberty"))(m.status[0])')(msg)
    assert compile_filter('m > 2')(3) and not compile_filter('m > 2')(1)


@pytest.mark.parametrize('expression, problem', [
    ('m.data >', "--filter 'm.data >': not a Python expression"),
    ('data > 3', "--filter 'data > 3': unknown name data (the message is m"),
    ('x = 3', "--filter 'x = 3': not a Python expression"),
])
def test_bad_filters_are_refused_at_once(expression, problem):
    with pytest.raises(FilterError) as caught:
        compile_filter(expression)
    assert str(caught.value).startswith(problem) and '\n' not in str(caught.value)


def test_a_filter_failing_on_a_message_raises_one_line():
    accept = compile_filter('m.status[3].level == 1')
    with pytest.raises(FilterError, match=r"^--filter 'm.status\[3\].level == 1': IndexError: "):
        accept(diagnostics(1))
    with pytest.raises(FilterError, match='AttributeError'):
        compile_filter('m.nope')(diagnostics(1))


# -- arguments ---------------------------------------------------------------------------------

def test_arguments_take_the_type_after_options_and_once_as_one():
    from inhand_tools.commands.topic_echo import parse_args, request_of
    args = parse_args(['diag', '--once', '-l', '8', 'diagnostic_msgs/DiagnosticArray', '--csv'])
    assert args.count == 1 and args.message_type == 'diagnostic_msgs/DiagnosticArray'
    request = request_of(args)
    assert request.msg_class is DiagnosticArray and request.count == 1
    assert request.text.truncate_length == 8 and request.text.csv
    assert request.accept is None and request.depth == 100
    request = request_of(parse_args(['diag', '--type', 'diagnostic_msgs/msg/DiagnosticArray',
                                     '--filter', 'm.header.stamp.sec > 1', '--qos-depth', '3',
                                     '--qos-reliability', 'best_effort']))
    assert request.msg_class is DiagnosticArray and request.depth == 3
    assert request.reliability == 'best_effort' and request.durability is None
    assert request.accept(diagnostics(2)) and not request.accept(diagnostics(1))


# -- the executable over DDS -----------------------------------------------------------------

def run_echo(*args, timeout: float = 30.0) -> subprocess.CompletedProcess:
    return subprocess.run([executable_path('topic_echo'), *args], capture_output=True,
                          text=True, timeout=timeout)


@contextlib.contextmanager
def publishing(topic: str, make=diagnostics, period: float = 0.02):
    """Publishes ``make(k)``, k = 0, 1, ..., every ``period`` s until the block ends."""
    talker = BackgroundNode('test_echo_talker')
    publisher = talker.node.create_publisher(type(make(0)), topic, 100)
    stop = threading.Event()

    def loop():
        k = 0
        while not stop.is_set():
            publisher.publish(make(k))
            k += 1
            stop.wait(period)

    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    try:
        yield publisher
    finally:
        stop.set()
        thread.join(5)
        talker.close()


def documents(stdout: str) -> list:
    return [d for d in yaml.safe_load_all(stdout) if d is not None]


@pytest.mark.dds
def test_once_prints_one_diagnostic_array_with_every_key():
    with publishing('echo_e2e/diag'):
        result = run_echo('echo_e2e/diag', '--once')
    assert result.returncode == 0, result.stderr
    assert result.stdout.count('---') == 1 and result.stdout.endswith('---\n')
    (document,) = documents(result.stdout)
    status = document['status'][0]
    k = document['header']['stamp']['sec']
    assert [v['key'] for v in status['values']] == [f'key{i}' for i in range(KEYS)]
    assert [v['value'] for v in status['values']] == [str(i * k) for i in range(KEYS)]
    assert status['name'] == 'liberty: driver' and status['level'] == k % 3
    assert '/echo_e2e/diag (diagnostic_msgs/msg/DiagnosticArray; reliable, volatile' in \
        result.stderr


@pytest.mark.dds
def test_csv_prints_one_line_per_message_with_the_qos_asked_for():
    with publishing('echo_e2e/csv'):
        result = run_echo('echo_e2e/csv', '--csv', '-n', '3', '--qos-reliability', 'best_effort',
                          '--qos-depth', '7')
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert len(lines) == 3 and '---' not in result.stdout
    rows = [line.split(',') for line in lines]
    assert all(len(row) == 7 + 2 * KEYS for row in rows)
    seconds = [int(row[0]) for row in rows]
    assert seconds == list(range(seconds[0], seconds[0] + 3))
    for k, row in zip(seconds, rows):
        assert row[1:7] == ['0', 'liberty', str(k % 3), 'liberty: driver', 'ok', 'tracker']
        assert row[7:] == [item for i in range(KEYS) for item in (f'key{i}', str(i * k))]
    assert 'best-effort, volatile, depth 7' in result.stderr


@pytest.mark.dds
def test_filter_prints_only_matching_messages_and_refuses_a_failing_one():
    topic = 'echo_e2e/filter'
    commands = {
        'message': [topic, '--filter', 'm.header.stamp.sec % 4 == 0', '-n', '3', '-l', '2'],
        'field': [topic, '--field', 'header.stamp.sec', '--filter', 'm % 4 == 1', '-n', '2'],
        'failing': [topic, '--filter', 'm.status[5].level == 0'],
    }
    with publishing(topic, period=0.01):
        runs = {name: subprocess.Popen([executable_path('topic_echo'), *args], text=True,
                                       stdout=subprocess.PIPE, stderr=subprocess.PIPE)
                for name, args in commands.items()}
        out = {name: (run.communicate(timeout=30), run.returncode) for name, run in runs.items()}
    (stdout, stderr), code = out['message']
    assert code == 0, stderr
    seconds = [d['header']['stamp']['sec'] for d in documents(stdout)]
    assert len(seconds) == 3 and all(s % 4 == 0 for s in seconds)
    assert seconds == [seconds[0], seconds[0] + 4, seconds[0] + 8]
    assert all(len(d['status'][0]['values']) == 3 for d in documents(stdout))  # -l 2: 2 and '...'
    (stdout, stderr), code = out['field']
    assert code == 0, stderr
    values = [int(line) for line in stdout.split()]
    assert len(values) == 2 and values[0] % 4 == 1 and values[1] == values[0] + 4
    (stdout, stderr), code = out['failing']
    assert code == 2 and stdout == ''
    assert stderr.splitlines()[-1] == \
        "topic_echo: --filter 'm.status[5].level == 0': IndexError: list index out of range"
    assert 'Traceback' not in stderr


@pytest.mark.dds
def test_a_type_given_before_the_topic_exists_waits_for_it():
    with running(['topic_echo', 'echo_e2e/late', 'diagnostic_msgs/DiagnosticArray', '-n', '2',
                  '--field', 'status[0].values[20].value']) as echo:
        deadline = time.monotonic() + 20
        while 'waiting for a publisher on /echo_e2e/late' not in echo.output():
            assert time.monotonic() < deadline and echo.alive(), echo.output()
            time.sleep(0.05)
        with publishing('echo_e2e/late'):
            assert echo.popen.wait(20) == 0, echo.output()
    lines = echo.output().splitlines()
    values = [int(line) for line in lines if line.isdigit()]
    assert len(values) == 2 and values[1] - values[0] == 20  # value 20 is 20 * k
    assert any('/echo_e2e/late (diagnostic_msgs/msg/DiagnosticArray;' in line for line in lines)


@pytest.mark.dds
def test_a_type_that_is_not_the_graphs_is_refused_in_one_line():
    with publishing('echo_e2e/text', make=lambda k: String(data=str(k))):
        result = run_echo('echo_e2e/text', 'diagnostic_msgs/msg/DiagnosticArray')
        unknown = run_echo('echo_e2e/text', 'diagnostic_msgs/msg/Nope')
    assert result.returncode == 2, result.stdout + result.stderr
    assert result.stderr.splitlines()[-1] == ('topic_echo: /echo_e2e/text is published as '
                                              'std_msgs/msg/String, not '
                                              'diagnostic_msgs/msg/DiagnosticArray')
    assert result.stdout == '' and 'Traceback' not in result.stderr
    assert unknown.returncode == 2
    assert unknown.stderr == ("topic_echo: unknown message type 'diagnostic_msgs/msg/Nope': "
                              'module diagnostic_msgs.msg has no message Nope\n')
