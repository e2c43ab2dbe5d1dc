"""A pseudo-terminal that looks like the Liberty's serial port, and can be 'unplugged'.

The device side keeps the master end; clients open a stable symlink (e.g.
``/tmp/liberty0``) that points at the current slave, as udev would name a USB serial
port. ``unplug()`` closes both ends and removes the link, so a client's reads fail and
its re-opens find nothing, like a pulled USB cable; ``plug()`` brings a fresh pty back
under the same name.
"""

from __future__ import annotations

import errno
import os
import select
import tty
from pathlib import Path

__all__ = ['PtyLink']


class PtyLink:
    def __init__(self, link_path: str | os.PathLike | None = None):
        self.link_path = Path(link_path) if link_path else None
        self.master: int | None = None
        self._slave: int | None = None
        self.slave_name: str | None = None
        self.plug()

    @property
    def port(self) -> str:
        """The name clients should open: the symlink if there is one, else the slave."""
        return str(self.link_path) if self.link_path else self.slave_name

    @property
    def connected(self) -> bool:
        return self.master is not None

    def plug(self) -> None:
        if self.connected:
            return
        master, slave = os.openpty()
        # Raw mode on the slave: no echo of what the device writes, no CR/LF rewriting.
        # Keeping our own slave descriptor open keeps these settings and the pty alive
        # while no client has the port open.
        tty.setraw(slave)
        os.set_blocking(master, False)
        self.master, self._slave = master, slave
        self.slave_name = os.ttyname(slave)
        if self.link_path:
            tmp = self.link_path.with_name(self.link_path.name + '.tmp')
            tmp.unlink(missing_ok=True)
            os.symlink(self.slave_name, tmp)
            os.replace(tmp, self.link_path)  # atomic: clients never see a missing link

    def unplug(self) -> None:
        if self.link_path:
            try:
                if self.link_path.is_symlink() and os.readlink(self.link_path) == self.slave_name:
                    self.link_path.unlink()
            except OSError:
                pass
        for fd in (self.master, self._slave):
            if fd is not None:
                os.close(fd)
        self.master = self._slave = None

    close = unplug

    def read(self, timeout: float) -> bytes:
        """Bytes the client wrote (b'' if none arrived within ``timeout`` seconds)."""
        if self.master is None:
            return b''
        ready, _, _ = select.select([self.master], [], [], max(timeout, 0.0))
        if not ready:
            return b''
        try:
            return os.read(self.master, 4096)
        except OSError as error:  # EIO: no client has the slave open right now
            if error.errno in (errno.EIO, errno.EAGAIN):
                return b''
            raise

    def write(self, data: bytes) -> int:
        """Write what fits without blocking; returns the count written (0 when full)."""
        if self.master is None or not data:
            return 0
        try:
            return os.write(self.master, data)
        except BlockingIOError:
            return 0
        except OSError as error:
            if error.errno in (errno.EIO, errno.EAGAIN):
                return 0
            raise
