"""The editor's HTTP server: the static web app, JSON endpoints and an event stream.

Standard library only (:class:`http.server.ThreadingHTTPServer`): one thread per connection,
the state in one :class:`~wiggly.editor.session.Session`.

Endpoints (JSON bodies are objects; errors answer ``{"error": message}``)::

    GET  /                     the app (static/index.html and its files)
    GET  /api/state            scene, resolved groups, version, the tab's undo/redo, dirty,
                               notices, the process's instance id, the size limits
    GET  /api/mesh             rest surface, binary (uint32 n, m; float32 n*3; uint32 m*3)
    GET  /api/frames/<id>      playback frames, binary float32 (F, n, 3)
    GET  /api/frames/latest    the newest frames (?final=1: newest final ones); meta in the
                               X-Wiggly-Frames header
    GET  /api/driver           the [drive] driver's keyed frames, binary float32 (F, n, 3);
                               their shot times and groups in the X-Wiggly-Driver header
    GET  /api/events           Server-Sent Events: state, frames, solve, physics, export,
                               notice (?page=ID: when it ends, that page's drag is abandoned;
                               &tab=ID: the tab is live while one of its pages listens)
    GET  /api/files            scene and mesh files inside the sandbox
    POST /api/edit             an edit {"op": ...} (see wiggly.editor.state), logged:
                               answered once its undo journal line is on the disk (507 if
                               the journal cannot be written; nothing changes then)
    POST /api/preview          the same, solved (linear) but not logged: gizmo drags
    POST /api/preview/cancel   a drag was abandoned: show the scene's frames again
    POST /api/undo, /api/redo  the tab's last edit (its own history, kept across restarts and
                               crashes; journaled like an edit)
    POST /api/open             {"path": "scene.toml" | "mesh.obj" | "builtin:critter"}
    POST /api/save             {"path": optional}
    POST /api/export           {"paths": ["out/shot.glb", ...], "overwrite": false}
    PUT  /api/upload?name=F    a mesh file as the raw body, stored in <first root>/uploads/

Edits, undo and redo belong to the tab named by the ``X-Wiggly-Tab`` header (each browser tab
has its own undo history; requests without it share the tab "api"; a new tab takes over the
history of a tab that is gone, so that a restart or a crashed browser leaves no edit that
cannot be undone).  A drag's previews
belong to the page load named by ``X-Wiggly-Page`` (a reload is a new page): a page that is
reloaded, closed or crashes mid-drag leaves no preview on the other tabs.

Safety: binds to 127.0.0.1 unless told otherwise; answers only requests whose ``Host`` is the
address it listens on (or localhost) when bound to a loopback address (DNS rebinding); refuses
cross-origin requests (``Origin`` must match) and JSON posted as anything but
``application/json`` (so another web page cannot forge requests); bodies larger than the
limits are refused with 413 before they are read, JSON nested deeper than
:data:`MAX_JSON_DEPTH` with 400; paths go through the sandbox; any error in a handler answers
4xx/5xx and leaves the session as it was.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import json
import mimetypes
import os
import queue
import re
import select
import socket
import threading
import traceback
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

import numpy as np

from wiggly.editor.history import TAB_ID, Histories
from wiggly.editor.scene_files import MESH_SUFFIXES, SCENE_SUFFIX
from wiggly.editor.session import Session
from wiggly.editor.state import EditError
from wiggly.errors import WigglyInputError

__all__ = ["MAX_JSON_BYTES", "MAX_JSON_DEPTH", "MAX_UPLOAD_BYTES", "EditorServer"]

MAX_JSON_BYTES = 8 * 2**20
MAX_JSON_DEPTH = 32  # nesting of arrays and objects (a scene needs 5)
MAX_UPLOAD_BYTES = 64 * 2**20
MAX_CONNECTIONS = 128
HEARTBEAT_SECONDS = 10.0
STREAM_POLL_SECONDS = 0.5  # how soon a closed event stream is noticed
STATIC = Path(str(resources.files("wiggly.editor") / "static"))
_TYPES = {".js": "text/javascript", ".html": "text/html", ".css": "text/css",
          ".txt": "text/plain", ".md": "text/plain", ".svg": "image/svg+xml"}


def _peer_closed(conn: socket.socket) -> bool:
    """Whether the client closed (or reset) ``conn``: an event stream's client sends nothing
    after its request, so a readable socket is at its end."""
    try:
        readable, _, _ = select.select([conn], [], [], 0)
        return bool(readable) and conn.recv(1, socket.MSG_PEEK) == b""
    except (OSError, ValueError):
        return True


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    server_version = "wiggly-editor"
    timeout = 30  # seconds of socket inactivity before a connection is dropped
    server: EditorServer

    # --- plumbing -------------------------------------------------------------------------
    def log_message(self, format: str, *args: Any) -> None:
        if self.server.verbose:
            super().log_message(format, *args)

    def _send(self, status: int, body: bytes, ctype: str = "application/json",
              headers: dict[str, str] | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, obj: Any, status: int = 200) -> None:
        self._send(status, dumps(obj))

    def _error(self, status: int, message: str) -> None:
        self.close_connection = True  # unread request bodies must not be parsed as requests
        self._send(status, dumps({"error": message}), headers={"Connection": "close"})

    def _allowed(self) -> bool:
        """Host and Origin checks (DNS rebinding, cross-site requests)."""
        host = self.headers.get("Host", "")
        if self.server.check_host and host.rsplit(":", 1)[0].strip("[]") not in \
                self.server.host_names:
            self._error(403, f"requests for host {host!r} are not served")
            return False
        origin = self.headers.get("Origin")
        if origin is not None and origin != "null":
            if urlsplit(origin).netloc != host:
                self._error(403, "cross-origin requests are not allowed")
                return False
        return True

    def _body(self, limit: int) -> bytes | None:
        length = self.headers.get("Content-Length")
        if self.headers.get("Transfer-Encoding", "").lower() == "chunked":
            self._error(411, "send a Content-Length (chunked bodies are not accepted)")
            return None
        if length is None:
            self._error(411, "a Content-Length is required")
            return None
        try:
            n = int(length)
        except ValueError:
            self._error(400, f"invalid Content-Length {length!r}")
            return None
        if n < 0:
            self._error(400, "invalid Content-Length")
            return None
        if n > limit:
            self._error(413, f"request body of {n} bytes exceeds the limit of {limit} bytes")
            return None
        data = self.rfile.read(n)
        if len(data) != n:
            self._error(400, "request body shorter than its Content-Length")
            return None
        return data

    def _json_body(self) -> Any:
        ctype = self.headers.get("Content-Type", "").split(";")[0].strip().lower()
        if ctype != "application/json":
            self._error(415, "send JSON with Content-Type: application/json")
            return _NOTHING
        data = self._body(self.server.max_json)
        if data is None:
            return _NOTHING
        if not data:
            return {}
        try:
            body = json.loads(data)
            deep = not _shallow(body)
        except (ValueError, UnicodeDecodeError) as err:
            self._error(400, f"invalid JSON: {err}")
            return _NOTHING
        except RecursionError:  # nested beyond what the parser follows
            deep = True
        if deep:
            self._error(400, f"JSON nested deeper than {MAX_JSON_DEPTH} levels is not accepted")
            return _NOTHING
        return body

    @property
    def tab(self) -> str:
        """The browser tab of the request (its undo history): the ``X-Wiggly-Tab`` header,
        or the event stream's ``tab`` query parameter."""
        query = parse_qs(urlsplit(self.path).query).get("tab")
        return Histories.tab_id(self.headers.get("X-Wiggly-Tab") or (query[0] if query else None))

    @property
    def page(self) -> str | None:
        """The page load of the request (a reload is a new one): the ``X-Wiggly-Page``
        header, or the event stream's ``page`` query parameter."""
        query = parse_qs(urlsplit(self.path).query).get("page")
        value = self.headers.get("X-Wiggly-Page") or (query[0] if query else None)
        if value is None or value == "":
            return None
        if not TAB_ID.fullmatch(value):
            raise EditError("the page id must be 1 to 64 letters, digits, '_' or '-'")
        return value

    def _dispatch(self, table: dict) -> None:
        try:
            if not self._allowed():
                return
            path = urlsplit(self.path).path
            for pattern, handler in table.items():
                m = re.fullmatch(pattern, path)
                if m:
                    handler(self, *m.groups())
                    return
            if self.command in ("GET", "HEAD"):
                self._static(path)
            else:
                self._error(404, f"no endpoint {self.command} {path}")
        except EditError as err:
            self._error(err.status, str(err))
        except WigglyInputError as err:
            self._error(400, str(err))
        except (BrokenPipeError, ConnectionResetError, TimeoutError):
            self.close_connection = True
        except Exception as err:  # a bug: answer 500, keep serving
            traceback.print_exc()
            try:
                self._error(500, f"internal error: {type(err).__name__}: {err}")
            except OSError:
                self.close_connection = True

    def do_GET(self) -> None:
        self._dispatch(_GET)

    def do_HEAD(self) -> None:
        self._dispatch(_GET)

    def do_POST(self) -> None:
        self._dispatch(_POST)

    def do_PUT(self) -> None:
        self._dispatch(_PUT)

    # --- static files ---------------------------------------------------------------------
    def _static(self, path: str) -> None:
        rel = "index.html" if path in ("", "/") else path.lstrip("/")
        if "\x00" in rel or len(rel) > 1024:
            self._error(404, f"no such file {path[:80]!r}")
            return
        f = Path(os.path.realpath(STATIC / rel))
        if not f.is_relative_to(Path(os.path.realpath(STATIC))) or not f.is_file():
            self._error(404, f"no such file {path}")
            return
        ctype = _TYPES.get(f.suffix) or mimetypes.guess_type(f.name)[0] or \
            "application/octet-stream"
        self._send(200, f.read_bytes(), ctype + ("; charset=utf-8" if ctype.startswith("text")
                                                 else ""))

    # --- GET ------------------------------------------------------------------------------
    def get_favicon(self) -> None:
        self._send(204, b"", "image/x-icon")

    def get_state(self) -> None:
        self._json(self.server.session.describe(self.tab))

    def get_mesh(self) -> None:
        self._send(200, self.server.session.mesh_bytes(), "application/octet-stream")

    def get_frames(self, frame_id: str) -> None:
        fs = self.server.session.frames(int(frame_id))
        self._send(200, fs.positions.astype("<f4", copy=False).tobytes(),
                   "application/octet-stream", {"X-Wiggly-Frames": json.dumps(fs.meta())})

    def get_latest_frames(self) -> None:
        query = parse_qs(urlsplit(self.path).query)
        fs = self.server.session.latest_frames(final=query.get("final", ["0"])[0] == "1")
        if fs is None:
            self._error(404, "no frames yet")
            return
        self._send(200, fs.positions.astype("<f4", copy=False).tobytes(),
                   "application/octet-stream", {"X-Wiggly-Frames": json.dumps(fs.meta())})

    def get_driver(self) -> None:
        data, meta = self.server.session.driver_frames()
        self._send(200, data, "application/octet-stream", {"X-Wiggly-Driver": json.dumps(meta)})

    def get_files(self) -> None:
        sb = self.server.session.sandbox
        self._json({"scenes": sb.listing((SCENE_SUFFIX,)), "meshes": sb.listing(MESH_SUFFIXES),
                    "unsaved": self.server.session.recoverable(),
                    "builtin": ["builtin:critter", "builtin:plant", "builtin:bar"]})

    def get_events(self) -> None:
        session = self.server.session
        bus = session.bus
        page, tab = self.page, self.tab
        if bus.n_subscribers >= self.server.max_streams:
            self._error(503, "too many open event streams")
            return
        q = bus.subscribe()
        session.page_opened(tab)
        self.close_connection = True
        try:
            self.send_response(200)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.send_header("Connection", "close")
            self.end_headers()
            self.wfile.write(b"retry: 1000\n\n")
            self.wfile.flush()
            quiet = 0.0
            while not self.server.stopping.is_set():
                try:
                    event = q.get(timeout=STREAM_POLL_SECONDS)
                except queue.Empty:
                    if _peer_closed(self.connection):
                        break
                    quiet += STREAM_POLL_SECONDS
                    if quiet >= HEARTBEAT_SECONDS:
                        self.wfile.write(b": keep-alive\n\n")
                        self.wfile.flush()
                        quiet = 0.0
                    continue
                self.wfile.write(b"data: " + dumps(event) + b"\n\n")
                self.wfile.flush()
        except OSError:
            pass
        finally:
            bus.unsubscribe(q)
            session.page_closed(page, tab)

    # --- POST -----------------------------------------------------------------------------
    def _post(self, fn) -> None:
        body = self._json_body()
        if body is _NOTHING:
            return
        self._json(fn(body))

    def post_edit(self) -> None:
        tab = self.tab
        self._post(lambda op: self.server.session.edit(op, tab))

    def post_preview(self) -> None:
        page = self.page
        self._post(lambda op: self.server.session.preview(op, page))

    def post_cancel_preview(self) -> None:
        page = self.page
        self._post(lambda _: self.server.session.cancel_preview(page))

    def post_undo(self) -> None:
        tab = self.tab
        self._post(lambda _: self.server.session.undo(tab))

    def post_redo(self) -> None:
        tab = self.tab
        self._post(lambda _: self.server.session.redo(tab))

    def post_open(self) -> None:
        tab = self.tab

        def run(body: dict) -> dict:
            out = self.server.session.open(_field(body, "path", str))
            self._tell_other_tabs(tab, f"another tab opened {out['path']}: this tab shows it "
                                       "now")
            return out

        self._post(run)

    def post_save(self) -> None:
        tab = self.tab

        def run(body: dict) -> dict:
            session = self.server.session
            before = session.scene.source  # (no scene open: 409, as save says)
            out = session.save(_field(body, "path", str, required=False),
                               _field(body, "overwrite", bool, False, required=False))
            if session.scene.source != before:
                self._tell_other_tabs(tab, f"another tab saved the scene as {out['path']}: "
                                           "this tab edits that file now")
            return out

        self._post(run)

    def _tell_other_tabs(self, tab: str, message: str) -> None:
        """A notice for every page but those of ``tab`` (which made the change itself)."""
        self.server.session.bus.publish("notice", sticky=False, level="info", message=message,
                                        from_tab=tab)

    def post_export(self) -> None:
        self._post(lambda b: self.server.session.export(_field(b, "paths", list),
                                                        _field(b, "overwrite", bool, False,
                                                               required=False)))

    # --- PUT ------------------------------------------------------------------------------
    def put_upload(self) -> None:
        if self.headers.get("X-Wiggly-Upload") != "1":
            self._error(400, "uploads need the header X-Wiggly-Upload: 1")
            return
        name = parse_qs(urlsplit(self.path).query).get("name", [""])[0]
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,120}", name) or \
                Path(name).suffix.lower() not in MESH_SUFFIXES:
            self._error(400, f"upload name {name[:80]!r} must be a plain file name ending in "
                             + ", ".join(MESH_SUFFIXES))
            return
        data = self._body(self.server.max_upload)
        if data is None:
            return
        folder = self.server.session.sandbox.home / "uploads"
        folder.mkdir(exist_ok=True)
        target = folder / name
        stem, k = target.stem, 1
        while target.exists():
            target = folder / f"{stem}-{k}{target.suffix}"
            k += 1
        target = self.server.session.sandbox.resolve(str(target))
        tmp = target.with_name(f".{target.name}.part")
        tmp.write_bytes(data)
        os.replace(tmp, target)
        self._json({"path": self.server.session.sandbox.relative(target), "bytes": len(data)})


_NOTHING = object()


def _shallow(obj: Any) -> bool:
    """Whether ``obj`` (parsed JSON) nests at most :data:`MAX_JSON_DEPTH` levels."""
    stack = [(obj, 1)]
    while stack:
        o, depth = stack.pop()
        children = o.values() if isinstance(o, dict) else o if isinstance(o, list) else None
        if children is None:
            continue
        if depth > MAX_JSON_DEPTH:
            return False
        stack.extend((c, depth + 1) for c in children)
    return True


def _field(body: Any, key: str, kind: type, default: Any = None, required: bool = True) -> Any:
    if not isinstance(body, dict):
        raise EditError(f"the request body must be a JSON object; got {type(body).__name__}")
    if key not in body or body[key] is None:
        if required:
            raise EditError(f"the request needs the field {key!r}")
        return default
    v = body[key]
    if not isinstance(v, kind) or (kind is not bool and isinstance(v, bool)):
        raise EditError(f"{key} must be a {kind.__name__}; got {type(v).__name__}")
    return v


_GET = {r"/favicon.ico": _Handler.get_favicon, r"/api/state": _Handler.get_state,
        r"/api/mesh": _Handler.get_mesh,
        r"/api/frames/latest": _Handler.get_latest_frames,
        r"/api/frames/(\d{1,12})": _Handler.get_frames, r"/api/files": _Handler.get_files,
        r"/api/driver": _Handler.get_driver,
        r"/api/events": _Handler.get_events}
_POST = {r"/api/edit": _Handler.post_edit, r"/api/preview": _Handler.post_preview,
         r"/api/preview/cancel": _Handler.post_cancel_preview,
         r"/api/undo": _Handler.post_undo, r"/api/redo": _Handler.post_redo,
         r"/api/open": _Handler.post_open, r"/api/save": _Handler.post_save,
         r"/api/export": _Handler.post_export}
_PUT = {r"/api/upload": _Handler.put_upload}


class EditorServer(ThreadingHTTPServer):
    """The editor's HTTP server for one :class:`Session`.

    ``port=0`` picks a free port (see :attr:`url`).  :meth:`start` serves on a background
    thread (tests, ``wiggly edit``); :meth:`stop` shuts down the server and the session.
    """

    daemon_threads = True
    allow_reuse_address = True
    request_queue_size = 64

    def __init__(self, session: Session, host: str = "127.0.0.1", port: int = 0, *,
                 max_json: int = MAX_JSON_BYTES, max_upload: int = MAX_UPLOAD_BYTES,
                 max_streams: int = 16, max_connections: int = MAX_CONNECTIONS,
                 verbose: bool = False):
        self.session = session
        self._slots = threading.BoundedSemaphore(max_connections)
        self.max_json, self.max_upload, self.max_streams = max_json, max_upload, max_streams
        self.verbose = verbose
        self.stopping = threading.Event()
        self._open: set[socket.socket] = set()  # connections being served
        self._open_lock = threading.Lock()
        super().__init__((host, port), _Handler)
        self.host = host
        try:
            loopback = ipaddress.ip_address(host).is_loopback
        except ValueError:
            loopback = host == "localhost"
        self.check_host = loopback
        self.host_names = {host, "localhost", "127.0.0.1", "::1"}
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        return self.server_address[1]

    @property
    def url(self) -> str:
        host = self.host if ":" not in self.host else f"[{self.host}]"
        if host in ("0.0.0.0", "[::]"):
            host = "127.0.0.1"
        return f"http://{host}:{self.port}/"

    def start(self) -> EditorServer:
        self.session.serving(self.url)
        self._thread = threading.Thread(target=self.serve_forever, kwargs={"poll_interval": 0.1},
                                        name="wiggly-editor-http", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving: the listening socket and every open connection (a browser's
        keep-alive connection must not be answered by a stopped session) are closed."""
        self.stopping.set()
        self.shutdown()
        self.server_close()
        with self._open_lock:
            open_connections = list(self._open)
        for conn in open_connections:
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        self.session.close()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def process_request(self, request, client_address) -> None:
        """One thread per connection, at most ``max_connections`` at once (others are closed
        right away)."""
        if not self._slots.acquire(blocking=False):
            self.shutdown_request(request)
            return
        with self._open_lock:
            self._open.add(request)
        super().process_request(request, client_address)

    def process_request_thread(self, request, client_address) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            with self._open_lock:
                self._open.discard(request)
            self._slots.release()

    def handle_error(self, request, client_address) -> None:  # never let a request kill us
        if self.verbose:
            super().handle_error(request, client_address)


def dumps(obj: Any) -> bytes:
    """JSON for the page: numpy arrays and scalars, paths and dataclasses included."""
    return json.dumps(obj, separators=(",", ":"), default=_default).encode()


def _default(o: Any):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    if dataclasses.is_dataclass(o):
        return dataclasses.asdict(o)
    raise TypeError(f"cannot serialize {type(o).__name__}")
