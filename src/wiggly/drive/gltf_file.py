"""The glTF 2.0 container: the JSON document as dicts, its buffers and typed accessors
(glTF 2.0 specification, sections 3.6 "Buffers, Buffer Views, and Accessors" and 4.4 "GLB
File Format Specification").

pygltflib's data model drops fields a driver needs (a node's morph ``weights``), so the
container is read here: a ``.glb`` is a 12-byte header and chunks (JSON, then BIN); a
``.gltf`` is the JSON, with buffers in data URIs or files beside it.
"""

from __future__ import annotations

import base64
import json
import struct
from pathlib import Path
from urllib.parse import unquote

import numpy as np

from wiggly.errors import WigglyInputError

__all__ = ["GltfFile"]

_COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16,
               5125: np.uint32, 5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_JSON_CHUNK, _BIN_CHUNK = 0x4E4F534A, 0x004E4942
#: Extensions that change how geometry is stored: a reader that ignores them reads garbage.
GEOMETRY_EXTENSIONS = ("KHR_draco_mesh_compression", "EXT_meshopt_compression")


class GltfFile:
    """A glTF document (``doc``: its JSON) with its buffers, and its accessors as arrays."""

    def __init__(self, path: Path):
        self.path = Path(path)
        try:
            data = self.path.read_bytes()
        except OSError as e:
            raise self.fail(e.strerror or str(e)) from None
        blob = None
        text = data
        if data[:4] == b"glTF":
            text, blob = self._chunks(data)
        try:
            self.doc = json.loads(text.decode("utf-8"))
        except (UnicodeDecodeError, ValueError) as e:
            raise self.fail(f"not a glTF file (its JSON does not parse: {e})") from None
        if not isinstance(self.doc, dict) or not str(
                (self.doc.get("asset") or {}).get("version", "")).startswith("2"):
            raise self.fail("not a glTF 2.0 file (asset.version is not 2.x)")
        required = [e for e in self.list("extensionsRequired") if e in GEOMETRY_EXTENSIONS]
        if required:
            raise self.fail(f"its geometry is compressed ({', '.join(required)}); export it "
                            "without compression")
        self.buffers = [self._buffer(i, b, blob) for i, b in enumerate(self.list("buffers"))]

    def fail(self, message: str) -> WigglyInputError:
        """An error naming the file."""
        return WigglyInputError(f"cannot read {self.path}: {message}")

    def list(self, key: str) -> list:
        """A top-level array of the document (``nodes``, ``meshes``, ...); [] if absent."""
        return self.doc.get(key) or []

    def item(self, key: str, index, what: str | None = None) -> dict:
        """``doc[key][index]``, or an error naming what refers to it."""
        items = self.list(key)
        if not isinstance(index, int) or not 0 <= index < len(items):
            raise self.fail(f"{what or key} refers to {key}[{index}], which does not exist")
        return items[index]

    def _chunks(self, data: bytes) -> tuple[bytes, bytes | None]:
        """The JSON and BIN chunks of a ``.glb`` container."""
        if len(data) < 20:
            raise self.fail("a glTF binary shorter than its header")
        version, length = struct.unpack_from("<II", data, 4)
        if version != 2:
            raise self.fail(f"glTF binary version {version}; only version 2 is read")
        pos, text, blob = 12, None, None
        while pos + 8 <= min(length, len(data)):
            size, kind = struct.unpack_from("<II", data, pos)
            chunk = data[pos + 8:pos + 8 + size]
            if len(chunk) != size:
                raise self.fail("a chunk runs past the end of the file (truncated?)")
            if kind == _JSON_CHUNK and text is None:
                text = chunk
            elif kind == _BIN_CHUNK and blob is None:
                blob = chunk
            pos += 8 + size
        if text is None:
            raise self.fail("the glTF binary has no JSON chunk")
        return text, blob

    def _buffer(self, i: int, buffer: dict, blob: bytes | None) -> bytes:
        uri = buffer.get("uri")
        if uri is None:
            if blob is None or i != 0:
                raise self.fail(f"buffer {i} has no data")
            return blob
        if uri.startswith("data:"):
            try:
                return base64.b64decode(uri.split(",", 1)[1])
            except (IndexError, ValueError) as e:
                raise self.fail(f"buffer {i} has a malformed data URI ({e})") from None
        file = self.path.parent / unquote(uri)
        try:
            return file.read_bytes()
        except OSError as e:
            raise self.fail(f"buffer {i}: cannot read {file} ({e.strerror or e})") from None

    def accessor(self, index) -> np.ndarray:
        """Accessor ``index`` as a (count, width) array: float64 for float and normalized
        integer components (``c / max``, clamped at -1), the integer type otherwise; sparse
        substitutions applied."""
        acc = self.item("accessors", index, "a primitive or sampler")
        kind, ctype, count = acc.get("type"), acc.get("componentType"), acc.get("count", 0)
        if ctype not in _COMPONENTS or kind not in _WIDTH:
            raise self.fail(f"accessor {index} has an unknown layout ({ctype}, {kind})")
        dtype = np.dtype(_COMPONENTS[ctype]).newbyteorder("<")
        width = _WIDTH[kind]
        if kind in ("MAT2", "MAT3") and dtype.itemsize < 4:
            raise self.fail(f"accessor {index}: padded {kind} matrices are not supported")
        what = f"accessor {index}"
        if acc.get("bufferView") is None:
            out = np.zeros((count, width), dtype)
        else:
            out = self._view(acc["bufferView"], acc.get("byteOffset", 0), count, width, dtype,
                             what).copy()
        sparse = acc.get("sparse")
        if sparse and sparse.get("count"):
            n = sparse["count"]
            ind, val = sparse["indices"], sparse["values"]
            itype = np.dtype(_COMPONENTS.get(ind.get("componentType"), np.uint32))
            rows = self._view(ind["bufferView"], ind.get("byteOffset", 0), n, 1,
                              itype.newbyteorder("<"), what).ravel().astype(np.int64)
            vals = self._view(val["bufferView"], val.get("byteOffset", 0), n, width, dtype, what)
            if rows.size and rows.max() >= count:
                raise self.fail(f"{what}: sparse indices beyond its {count} elements")
            out[rows] = vals
        if acc.get("normalized") and np.issubdtype(dtype, np.integer):
            return np.maximum(out.astype(np.float64) / np.iinfo(dtype).max, -1.0)
        if dtype.kind == "f":
            return out.astype(np.float64)
        return out

    def _view(self, index, offset: int, count: int, width: int, dtype: np.dtype,
              what: str) -> np.ndarray:
        view = self.item("bufferViews", index, what)
        buffer = view.get("buffer")
        if not isinstance(buffer, int) or not 0 <= buffer < len(self.buffers):
            raise self.fail(f"bufferView {index} refers to buffer {buffer}, which does not "
                            "exist")
        data = self.buffers[buffer]
        elem = dtype.itemsize * width
        stride = view.get("byteStride") or elem
        base = view.get("byteOffset", 0)
        start = base + offset
        end = start + stride * (count - 1) + elem if count else start
        if end > min(len(data), base + view.get("byteLength", 0)):
            raise self.fail(f"{what} runs past the end of its bufferView {index}")
        return np.ndarray((count, width), dtype, buffer=data, offset=start,
                          strides=(stride, dtype.itemsize))
