"""The live view's web page over plain HTTP, served from a thread of its own (stdlib, no ROS).

``GET /`` is the page (``inhand_view/web/index.html`` with ``view.js`` and ``view.css``:
package data, nothing from the network), ``GET /state.json?since=V`` what it shows (the
map's cells only when the page's map version ``V`` is not the latest), ``POST /call/<name>``
runs one of the node's actions (``reset``, ``save``: the occupancy node's Trigger services)
and answers ``{"name", "success", "message"}``. Requests are handled by a thread each
(:class:`http.server.ThreadingHTTPServer`), so neither a slow browser nor a service call
that waits for its answer ever holds up the ROS executor.
"""

from __future__ import annotations

import json
import socket
import threading
from collections.abc import Callable, Mapping
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any
from urllib.parse import parse_qs, urlsplit

__all__ = ['PAGE_FILES', 'PageServer']

PAGE_FILES = {
    '/': ('index.html', 'text/html; charset=utf-8'),
    '/index.html': ('index.html', 'text/html; charset=utf-8'),
    '/view.js': ('view.js', 'text/javascript; charset=utf-8'),
    '/view.css': ('view.css', 'text/css; charset=utf-8'),
}

StateSource = Callable[[int | None], Mapping[str, Any]]
Action = Callable[[], tuple[bool, str]]


def page_file(name: str) -> bytes:
    """One of the page's files, from the package's ``web/`` folder."""
    return resources.files('inhand_view').joinpath('web', name).read_bytes()


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    protocol_version = 'HTTP/1.1'

    def log_message(self, format: str, *args: Any) -> None:
        pass   # one line per request on stderr is noise in a node's log

    def _send(self, status: HTTPStatus, body: bytes, content_type: str) -> None:
        self.send_response(status)
        self.send_header('Content-Type', content_type)
        self.send_header('Content-Length', str(len(body)))
        self.send_header('Cache-Control', 'no-store')
        self.end_headers()
        if self.command != 'HEAD':
            self.wfile.write(body)

    def _send_json(self, status: HTTPStatus, data: Mapping[str, Any]) -> None:
        self._send(status, json.dumps(data, separators=(',', ':')).encode('utf-8'),
                   'application/json')

    def _guarded(self, handle: Callable[[], None]) -> None:
        try:
            handle()
        except (BrokenPipeError, ConnectionResetError):
            pass                         # the browser left
        except Exception as error:       # a bug: said in the answer, kept for the node's log
            self.server.errors.append(f'{self.command} {self.path}: {type(error).__name__}: '
                                      f'{error}')
            self._send_json(HTTPStatus.INTERNAL_SERVER_ERROR, {'error': self.server.errors[-1]})

    def do_GET(self) -> None:
        self._guarded(self._get)

    do_HEAD = do_GET

    def do_POST(self) -> None:
        self._guarded(self._post)

    def _get(self) -> None:
        url = urlsplit(self.path)
        if url.path == '/state.json':
            since = parse_qs(url.query).get('since', [''])[0]
            self._send_json(HTTPStatus.OK, self.server.state(int(since) if since.isdigit()
                                                             else None))
        elif url.path in PAGE_FILES:
            name, content_type = PAGE_FILES[url.path]
            self._send(HTTPStatus.OK, page_file(name), content_type)
        else:
            self._send_json(HTTPStatus.NOT_FOUND, {'error': f'no {url.path} here'})

    def _post(self) -> None:
        length = int(self.headers.get('Content-Length') or 0)
        if length:
            self.rfile.read(length)          # the actions take no arguments
        name = urlsplit(self.path).path.removeprefix('/call/')
        action = self.server.actions.get(name) if self.path.startswith('/call/') else None
        if action is None:
            self._send_json(HTTPStatus.NOT_FOUND, {'error': f'no action {name!r}'})
            return
        try:
            success, message = action()
        except Exception as error:   # an action's failure is the page's answer, not a crash
            success, message = False, f'{type(error).__name__}: {error}'
        self._send_json(HTTPStatus.OK, {'name': name, 'success': success, 'message': message})


class _Server(ThreadingHTTPServer):
    daemon_threads = True

    def __init__(self, address: tuple[str, int], state: StateSource,
                 actions: Mapping[str, Action]):
        self.state = state
        self.actions = dict(actions)
        self.errors: list[str] = []      # what went wrong in requests, for the node's log
        if ':' in address[0]:
            self.address_family = socket.AF_INET6
        super().__init__(address, _Handler)


class PageServer:
    """Binds at construction (``OSError`` when the port is taken), serves from a daemon
    thread after :meth:`start` until :meth:`close`."""

    def __init__(self, host: str, port: int, state: StateSource, actions: Mapping[str, Action]):
        self._server = _Server((host, port), state, actions)
        self.host, self.port = host, int(self._server.server_address[1])
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host = '127.0.0.1' if self.host in ('', '0.0.0.0') else self.host
        host = f'[{host}]' if ':' in host else host
        return f'http://{host}:{self.port}/'

    def start(self) -> None:
        self._thread = threading.Thread(target=self._server.serve_forever,
                                        kwargs={'poll_interval': 0.2}, name='live_view_http',
                                        daemon=True)
        self._thread.start()

    def take_errors(self) -> list[str]:
        """What went wrong in requests since the last call (a bug in the state, an action)."""
        errors, self._server.errors[:] = list(self._server.errors), []
        return errors

    def close(self) -> None:
        if self._thread is not None:
            self._server.shutdown()
            self._thread.join(5.0)
        self._server.server_close()
