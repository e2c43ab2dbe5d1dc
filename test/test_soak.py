"""The soak script (test/benchmarks/soak.py) in one minute: every fault, a kill and a resume.

``benchmark.sh soak`` runs it for 30 minutes (figures in docs/reliability.md); here the same
checks run on a minute with a fault every 7 s, so that each kind comes at least once, and
the occupancy node killed half way and resumed from an autosave 5 s old.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from conftest import WORKSPACE

pytestmark = pytest.mark.dds


def test_a_minute_of_faults_and_a_kill_passes_the_soak_checks(tmp_path):
    out = tmp_path / 'soak'
    result = subprocess.run(
        [sys.executable, str(WORKSPACE / 'test' / 'benchmarks' / 'soak.py'), '--minutes', '1',
         '--fault-every', '7', '--autosave', '5', '--kill-at', '31', '--output', str(out)],
        capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-6000:] + result.stderr[-3000:]
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['faults'] == 8 and summary['crashes'] == 0 and summary['problems'] == []
    frames = summary['frames']
    # pause, stall and disconnect each stop the stream for over a second: seen as outages
    assert {'pause', 'stall', 'disconnect'} <= set(frames['outages_by_fault'])
    assert frames['outages_elsewhere'] == 0 and frames['skipped'] == 24
    assert frames['in_bag'] == frames['published'] > 10000
    resumed = summary['map']
    assert resumed['lost_to_kill'] > 0       # the kill lost what came after the autosave
    assert resumed['build_map_points'] == resumed['registered'] == \
        resumed['node_points'] + resumed['lost_to_kill']
    assert resumed['differing_beyond_reach'] == 0
    memory = summary['memory']
    assert {'driver', 'registration', 'occupancy', 'occupancy (restarted)', 'recorder',
            'emulator'} <= set(memory)
    assert (out / 'rss.png').stat().st_size > 5000 and (out / 'soak.log').exists()
