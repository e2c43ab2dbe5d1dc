"""How much memory this machine can give a process now (Linux's MemAvailable), for the
checks that refuse a configuration before it allocates what is not there.

No rclpy here.
"""

from __future__ import annotations

import os

__all__ = ['available_memory', 'human_bytes']


def available_memory(meminfo: str = '/proc/meminfo') -> int | None:
    """Bytes available to new allocations without swapping (MemAvailable), or None where
    the system does not say."""
    try:
        with open(meminfo) as lines:
            for line in lines:
                if line.startswith('MemAvailable:'):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf('SC_AVPHYS_PAGES') * os.sysconf('SC_PAGE_SIZE')
    except (ValueError, OSError, AttributeError):
        return None


def human_bytes(count: float) -> str:
    """1536 -> '1.5 KB', 2.4e10 -> '24.0 GB' (powers of 1024, as free -h)."""
    value = float(count)
    for unit in ('B', 'KB', 'MB', 'GB'):
        if abs(value) < 1024.0:
            return f'{value:.0f} {unit}' if unit == 'B' else f'{value:.1f} {unit}'
        value /= 1024.0
    return f'{value:.1f} TB'
