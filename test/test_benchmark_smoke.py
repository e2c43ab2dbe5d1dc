"""Smoke check of the benchmark script: its codec part runs, loses nothing and prints a rate.

Only the codec part (no ROS, no driver subprocess), in quick mode: a few seconds.
"""

import re
import subprocess
import sys
import time

SCRIPT = 'test/benchmarks/bench_liberty.py'


def test_codec_benchmark_quick_runs_and_reports_a_rate(workspace):
    start = time.monotonic()
    result = subprocess.run([sys.executable, str(workspace / SCRIPT), '--codec-only', '--quick'],
                            cwd=workspace, capture_output=True, text=True, timeout=60)
    elapsed = time.monotonic() - start
    assert result.returncode == 0, result.stdout + result.stderr
    rates = re.findall(r'^\s*(binary F1|ASCII F0): ([\d,]+) records/s', result.stdout, re.M)
    assert {name for name, _ in rates} == {'binary F1', 'ASCII F0'}, result.stdout
    assert all(int(rate.replace(',', '')) > 0 for _, rate in rates)
    assert result.stdout.count('no records lost') == 2, result.stdout
    assert elapsed < 15.0, f'quick codec benchmark took {elapsed:.1f} s'
