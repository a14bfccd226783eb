"""Atomic writers and validating readers for the project's file formats.

Every writer writes to a temporary sibling and renames, so an interrupted run
never leaves a half-written file under the final name. Every reader checks what
it reads and raises :class:`DataFormatError` naming the file and the problem.
The other stages (recon, billboards) read datasets through these functions too.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import math
import os
import shutil
import tokenize
import uuid
from pathlib import Path
from typing import Any, Iterator

import cv2
import numpy as np

from .errors import InputError
from .workdir import hidden_name

logger = logging.getLogger(__name__)

#: Refuse .npy arrays larger than this unless the caller allows more.
DEFAULT_MAX_NPY_BYTES = 1 << 31

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"IEND\xaeB`\x82"


class DataFormatError(InputError):
    """A file is missing, malformed or inconsistent; the message names it."""

    def __init__(self, path: os.PathLike | str, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self):
        # crosses process boundaries whole, subclasses too: the default re-calls __init__ with the message only
        return _rebuild_error, (type(self), self.args, self.__dict__)


def _rebuild_error(cls: type, args: tuple, state: dict) -> BaseException:
    error = cls.__new__(cls)
    error.args = args
    error.__dict__.update(state)
    return error


@contextlib.contextmanager
def atomic_path(path: os.PathLike | str) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it to ``path`` on success.

    On an exception the temporary file is removed and ``path`` is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{hidden_name(path.name)}.tmp-{os.getpid()}{path.suffix}")
    if tmp.is_symlink() or tmp.is_file():  # a dead run's, or planted: writing through a link would change its target
        tmp.unlink()
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as e:
        if e.filename is None:  # a write through a file object names no file
            raise _naming(e, path) from e
        raise
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def _naming(error: OSError, path: Path) -> OSError:
    """``error`` with ``path`` as its file; numpy's short writes ("N requested and M written",
    no errno) become ENOSPC when the disk is indeed full."""
    code, text = error.errno, error.strerror or str(error)
    if code is None and disk_full(path.parent):
        code, text = errno.ENOSPC, f"{os.strerror(errno.ENOSPC)} ({error})"
    return type(error)(code, text, str(path))


def disk_full(directory: os.PathLike | str) -> bool:
    """Whether the file system of ``directory`` has no block left (False when it cannot tell)."""
    try:
        return os.statvfs(directory).f_bavail == 0
    except OSError:
        return False


def replace_dir(tmp: Path, path: Path) -> None:
    """Rename the finished directory ``tmp`` to ``path``. A directory already at ``path`` is set
    aside (``.NAME.old-HEX``) and removed only once the new one is in place: put back if the
    rename fails, and by :func:`core.workdir.sweep_output` if the process dies in between. A
    file or link at ``path`` is never replaced (NotADirectoryError)."""
    tmp, path = Path(tmp), Path(path)
    if path.is_symlink() or (path.exists() and not path.is_dir()):
        raise NotADirectoryError(errno.ENOTDIR, "exists and is not a directory; not replacing it", str(path))
    if not path.exists():
        os.rename(tmp, path)
        return
    old = path.with_name(f".{hidden_name(path.name)}.old-{uuid.uuid4().hex}")
    os.rename(path, old)
    try:
        os.rename(tmp, path)
    except BaseException:
        os.rename(old, path)
        raise
    shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def atomic_dir(path: os.PathLike | str) -> Iterator[Path]:
    """Yield a new empty directory beside ``path``; on success it replaces ``path``
    (:func:`replace_dir`), on an exception it is removed and ``path`` is untouched."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{hidden_name(path.name)}.tmp-{uuid.uuid4().hex}")
    tmp.mkdir()
    try:
        yield tmp
        replace_dir(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_bytes(path: os.PathLike | str, data: bytes) -> Path:
    """Atomically write ``data`` to ``path``."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
    return Path(path)


def write_json(path: os.PathLike | str, obj: Any) -> Path:
    """Atomically write ``obj`` as indented JSON (float64 values round-trip exactly)."""
    text = json.dumps(obj, indent=1, allow_nan=False)
    return write_bytes(path, (text + "\n").encode())


def json_ready(value: Any) -> Any:
    """``value`` with non-finite floats as None (JSON null = no measurement) and numpy scalars as
    Python's, through dicts (keys as strings), lists and tuples (as lists): what :func:`write_json`
    takes, which refuses NaN."""
    if isinstance(value, dict):
        return {str(k): json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def read_json(path: os.PathLike | str, max_bytes: int | None = None) -> Any:
    """Read a JSON file; a missing or malformed file, or one over ``max_bytes``, raises
    :class:`DataFormatError`."""
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "file is missing")
    if max_bytes is not None and path.stat().st_size > max_bytes:
        raise DataFormatError(path, f"is larger than {max_bytes} bytes")
    try:
        return json.loads(path.read_bytes(), parse_constant=reject_json_constant)
    except (ValueError, UnicodeDecodeError, RecursionError) as e:  # JSONDecodeError is a ValueError
        raise DataFormatError(path, f"not valid JSON ({e})") from None


def reject_json_constant(name: str) -> None:
    """``json.loads(parse_constant=...)``: NaN and Infinity are not JSON."""
    raise InputError(f"{name} is not allowed")


def save_npy(path: os.PathLike | str, array: np.ndarray) -> Path:
    """Atomically save ``array`` as ``.npy`` (never pickled)."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, np.ascontiguousarray(array), allow_pickle=False)
    return Path(path)


def read_npy_header(path: os.PathLike | str) -> tuple[tuple, bool, np.dtype, int]:
    """(shape, fortran_order, dtype, data offset in bytes) of a ``.npy`` file, without reading
    its data; DataFormatError for a missing file or a header that is not a valid one."""
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "file is missing")
    try:
        with open(path, "rb") as f:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                header = np.lib.format.read_array_header_1_0(f, max_header_size=10000)
            elif version == (2, 0):
                header = np.lib.format.read_array_header_2_0(f, max_header_size=10000)
            else:
                raise DataFormatError(path, f"unsupported .npy format version {version}")
            offset = f.tell()
    except DataFormatError:
        raise
    # numpy parses the header with Python's tokenizer: garbage surfaces as SyntaxError/TokenError
    except (ValueError, TypeError, OSError, EOFError, OverflowError, SyntaxError, tokenize.TokenError,
            RecursionError, MemoryError) as e:
        raise DataFormatError(path, f"not a valid .npy array ({e})") from None
    shape, fortran, dtype = header
    return tuple(shape), bool(fortran), dtype, offset


def load_npy(
    path: os.PathLike | str,
    dtype: np.dtype | type | None = None,
    shape: tuple[int | None, ...] | None = None,
    finite: bool = False,
    max_bytes: int = DEFAULT_MAX_NPY_BYTES,
) -> np.ndarray:
    """Load a ``.npy`` array after checking its header.

    dtype: required dtype (exact), or None for any non-object dtype.
    shape: required shape; ``None`` entries match any length.
    finite: reject NaN/inf (floating arrays only).
    max_bytes: refuse arrays whose header claims more bytes than this.
    A file shorter or longer than its header says is refused.
    """
    path = Path(path)
    file_shape, _, file_dtype, offset = read_npy_header(path)
    if file_dtype.hasobject:
        raise DataFormatError(path, "holds Python objects (pickles are not loaded)")
    if any(n < 0 for n in file_shape):
        raise DataFormatError(path, f"header claims a negative shape {file_shape}")
    nbytes = math.prod(file_shape) * file_dtype.itemsize  # Python ints: no int64 overflow
    if nbytes > max_bytes:
        raise DataFormatError(path, f"array of {nbytes} bytes exceeds the limit of {max_bytes}")
    size = path.stat().st_size - offset
    if size > nbytes:  # a file written over another, or damaged: not the array its header describes
        raise DataFormatError(path, f"has {size - nbytes} bytes after the array data")
    try:
        array = np.load(path, allow_pickle=False)
    except (ValueError, TypeError, OSError, EOFError, OverflowError) as e:
        raise DataFormatError(path, f"not a valid .npy array ({e})") from None
    if dtype is not None and array.dtype != np.dtype(dtype):
        raise DataFormatError(path, f"dtype {array.dtype}, expected {np.dtype(dtype)}")
    if shape is not None:
        ok = array.ndim == len(shape) and all(s is None or s == a for s, a in zip(shape, array.shape))
        if not ok:
            want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
            raise DataFormatError(path, f"shape {array.shape}, expected {want}")
    if finite and array.dtype.kind == "f" and not np.all(np.isfinite(array)):
        raise DataFormatError(path, "contains NaN or inf")
    return array


def write_png(path: os.PathLike | str, rgb: np.ndarray) -> Path:
    """Atomically write an RGB image ``(h, w, 3) uint8`` (or grey ``(h, w)``) as PNG."""
    if rgb.dtype != np.uint8 or rgb.ndim not in (2, 3):
        raise InputError(f"write_png wants (h, w[, 3]) uint8, got {rgb.shape} {rgb.dtype}")
    image = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR) if rgb.ndim == 3 else rgb
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    return write_bytes(path, buf.tobytes())


def read_png(path: os.PathLike | str, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read a PNG as RGB ``(h, w, 3) uint8``.

    size: expected ``(width, height)``; a mismatch raises :class:`DataFormatError`,
    as do a missing, truncated or non-PNG file.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "image file is missing")
    data = path.read_bytes()
    if not data.startswith(_PNG_SIGNATURE):
        raise DataFormatError(path, "not a PNG file")
    # libpng may decode a cut-off file into a partly grey image; the IEND chunk
    # at the very end is the cheap, exact test that the file is complete.
    if not data.endswith(_PNG_IEND):
        raise DataFormatError(path, "PNG is truncated (no IEND chunk at the end)")
    if data[12:16] != b"IHDR":
        raise DataFormatError(path, "PNG has no IHDR chunk first")
    header_size = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if size is not None and header_size != tuple(size):  # refused before decoding (a huge image is a bomb)
        raise DataFormatError(
            path, f"image is {header_size[0]}x{header_size[1]}, expected {size[0]}x{size[1]}"
        )
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise DataFormatError(path, "PNG could not be decoded")
    rgb = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    if size is not None and (rgb.shape[1], rgb.shape[0]) != tuple(size):
        raise DataFormatError(
            path, f"image is {rgb.shape[1]}x{rgb.shape[0]}, expected {size[0]}x{size[1]}"
        )
    return rgb


def as_matrix(value: Any, shape: tuple[int, ...], path: Path, what: str) -> np.ndarray:
    """Convert a JSON value to a finite float64 array of ``shape`` or raise naming ``what``.
    Its entries must be JSON numbers: not booleans (Python's True is 1), nor numeric strings."""
    if not _numbers_only(value):
        raise DataFormatError(path, f"{what} must hold numbers only (no booleans, strings or null)")
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):  # an integer of 400 digits overflows float64
        raise DataFormatError(path, f"{what} is not a numeric array") from None
    if array.shape != shape:
        raise DataFormatError(path, f"{what} has shape {array.shape}, expected {shape}")
    if not np.all(np.isfinite(array)):
        raise DataFormatError(path, f"{what} contains NaN or inf")
    return array


def _numbers_only(value: Any) -> bool:
    if isinstance(value, np.ndarray):
        return value.dtype.kind in "iuf"
    if isinstance(value, (list, tuple)):
        return all(_numbers_only(v) for v in value)
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def check_rigid(T: np.ndarray, path: Path, what: str, tol: float = 1e-6) -> np.ndarray:
    """Check that ``T`` (4, 4) float64 is a rigid transform; return it."""
    R = T[:3, :3]
    if np.abs(T[3] - [0, 0, 0, 1]).max() > tol:
        raise DataFormatError(path, f"{what} last row is not [0, 0, 0, 1]")
    if np.abs(R.T @ R - np.eye(3)).max() > tol or abs(np.linalg.det(R) - 1) > tol:
        raise DataFormatError(path, f"{what} rotation is not orthonormal with det +1")
    return T
