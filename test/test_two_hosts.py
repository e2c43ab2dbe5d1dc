"""Two hosts joined by a veth pair, discovery by static peers only (launch_scripts/two_hosts.py).

Needs root and iproute2 to create network namespaces; where the machine cannot, the
script says why (exit 3) and the tests skip with that reason.
"""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

WORKSPACE = Path(__file__).resolve().parents[1]


def two_hosts(output, *extra):
    result = subprocess.run([sys.executable, str(WORKSPACE / 'launch_scripts' / 'two_hosts.py'),
                             '--duration', '5', '--output', str(output), *extra],
                            capture_output=True, text=True, timeout=180)
    if result.returncode == 3:
        pytest.skip(result.stderr.strip())
    return result


def test_the_map_arrives_from_the_tracker_host_over_the_veth(tmp_path):
    result = two_hosts(tmp_path)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    assert 'the map arrived' in result.stdout
    with np.load(tmp_path / 'two_hosts.npz') as saved:
        assert saved['hits'].sum() > 1000   # 5 s at 240 Hz x 3 fingertips, less discovery
    assert not [n for n in subprocess.run(['ip', 'netns', 'list'], capture_output=True,
                                          text=True).stdout.split() if n.startswith('inhand-')]


def test_without_static_peers_nothing_crosses_between_the_hosts(tmp_path):
    """The control: without the other host among the initial peers nothing crosses."""
    result = two_hosts(tmp_path, '--without-peers')
    assert result.returncode == 1, result.stdout[-3000:] + result.stderr[-2000:]
    assert 'registered 0 fingertip positions' in result.stdout
