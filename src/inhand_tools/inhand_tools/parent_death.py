"""Run a command that gets SIGTERM when the process that started it dies, however it dies.

    python -m inhand_tools.parent_death PARENT_PID COMMAND [ARG ...]

A launcher stops its nodes itself on Ctrl-C, SIGTERM and SIGHUP; ``kill -9`` of the
launcher gives it no chance, and its nodes (each in a session of its own) would run on as
orphans. Linux's parent-death signal (``prctl(PR_SET_PDEATHSIG)``) closes that gap: the
kernel sends SIGTERM to the command when its parent exits, and the nodes end as on any
SIGTERM (the occupancy node saves its map). The setting survives ``execvp``, so this module
sets it and becomes the command. ``subprocess``'s ``preexec_fn`` could do the same without
the extra start, but it is not safe in a process with threads, as a launcher is (one
thread per child's output).

PARENT_PID is the launcher's pid: if it is already gone when we get here (it died between
the fork and the prctl), the command is not started at all. Elsewhere than on Linux the
command just runs.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys

__all__ = ['command_with_parent_death', 'main']

PR_SET_PDEATHSIG = 1   # <sys/prctl.h>


def command_with_parent_death(command: list[str]) -> list[str]:
    """``command`` run through this module on behalf of the calling process."""
    return [sys.executable, '-m', 'inhand_tools.parent_death', str(os.getpid()), *command]


def _set_parent_death_signal(sig: int) -> bool:
    if not sys.platform.startswith('linux'):
        return False
    libc = ctypes.CDLL(None, use_errno=True)
    return libc.prctl(PR_SET_PDEATHSIG, sig, 0, 0, 0) == 0


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) < 2 or not args[0].isdigit():
        print('usage: python -m inhand_tools.parent_death PARENT_PID COMMAND [ARG ...]',
              file=sys.stderr)
        return 2
    parent, command = int(args[0]), args[1:]
    if _set_parent_death_signal(signal.SIGTERM) and os.getppid() != parent:
        return 1    # the launcher died before the signal was set: nothing to run for
    try:
        os.execvp(command[0], command)
    except OSError as error:
        print(f'parent_death: cannot run {command[0]}: {error}', file=sys.stderr)
        return 127
    return 0   # not reached: execvp replaced this process


if __name__ == '__main__':
    raise SystemExit(main())
