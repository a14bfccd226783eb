"""What the command line accepts: argparse ``type=`` functions for its numbers, the size
bounds the commands share, and the memory a command's sizes will need.

Each option is checked as argparse parses it, so a bad value ends the command with one
usage line naming the option (exit 2) before anything is read, written or allocated.
Numbers are finite (no nan or inf) unless an option says otherwise; a size is also
refused when the machine's available memory cannot hold what the command allocates for it.
"""

from __future__ import annotations

import argparse
import math
import os
import re

from core.errors import InputError

#: Largest texture and renderbuffer edge the renderers rely on (pixels, texels): the
#: GL_MAX_TEXTURE_SIZE / GL_MAX_RENDERBUFFER_SIZE of current desktop GPUs.
GL_MAX_SIZE = 16384

#: Largest billboard tile edge (texels); a tile of the default 32 directions at 256²
#: already holds 8 M texels per billboard.
MAX_TILE = 256


#: Longest synthetic street or town drive, metres.
MAX_LENGTH = 100_000.0

#: Most frames of a synthetic pass or a rendered path.
MAX_FRAMES = 100_000

#: Widest panel of eval's side-by-side images, pixels.
MAX_PANEL_WIDTH = 4096

#: Finest length the stages resolve (voxels, blocks, depths), metres: finer ones overflow
#: their integer grids (a denormal 1e-320 m voxel is an infinite number of cells).
MIN_LENGTH = 1e-4

#: Most repetitions of a timed benchmark section.
MAX_REPEATS = 100

#: Highest frame rate of a rendered video, frames per second.
MAX_FPS = 1000.0

#: Bytes per pixel of an offscreen render: RGBA8 colour and 32-bit depth renderbuffers,
#: the RGB read back and its flipped copy (14), rounded up.
RENDER_BYTES_PER_PIXEL = 16

#: Bytes per pixel of an eval view: the render, and about twenty float64 values per pixel
#: of ground truth, masks and the PSNR/SSIM work arrays.
EVAL_BYTES_PER_PIXEL = RENDER_BYTES_PER_PIXEL + 20 * 8

#: Bytes per sampled texel and direction in a build worker: the float32 stack, its
#: eigen images and decoded copy, and PCA's work arrays.
BUILD_BYTES_PER_TEXEL = 32
#: Bytes the fit's solve holds per unknown (float64 x, r, z, p, M·p and the right-hand side).
FIT_BYTES_PER_UNKNOWN = 48


class UsageError(InputError):
    """Bad command-line input: options that contradict each other, a value no option takes,
    a size the memory cannot hold. Before the command starts it becomes argparse's usage
    line; raised later, ``main`` reports it in one line like any bad input (exit 2)."""


def _fail(message: str):
    raise argparse.ArgumentTypeError(message)


def _parse_int(text: str) -> int:
    try:
        return int(text)
    except (TypeError, ValueError):
        _fail(f"expected an integer, got {text!r}")


def _parse_float(text: str, allow_inf: bool = False) -> float:
    try:
        value = float(text)
    except (TypeError, ValueError):
        _fail(f"expected a number, got {text!r}")
    if math.isnan(value) or (math.isinf(value) and not allow_inf):
        _fail(f"expected a finite number, got {text!r}")
    return value


def int_range(lo: int, hi: int | None = None, why: str = ""):
    """An argparse type: an integer in [lo, hi] (hi None: no upper bound); ``why`` says
    where hi comes from in the message."""
    def parse(text: str) -> int:
        value = _parse_int(text)
        if value < lo:
            _fail(f"must be at least {lo}, got {value}")
        if hi is not None and value > hi:
            _fail(f"must be at most {hi}{f' ({why})' if why else ''}, got {value}")
        return value
    parse.__name__ = f"int_range({lo}, {hi})"
    return parse


def float_range(lo: float | None = None, hi: float | None = None, *, lo_open: bool = True,
                hi_open: bool = False, allow_inf: bool = False):
    """An argparse type: a finite number in the interval from lo to hi, each end open or
    closed (None: unbounded); allow_inf also takes +inf/-inf where the interval holds them."""
    def parse(text: str) -> float:
        value = _parse_float(text, allow_inf)
        below = lo is not None and (value <= lo if lo_open else value < lo)
        above = hi is not None and (value >= hi if hi_open else value > hi)
        if below or above:
            left = "(-inf" if lo is None else f"{'(' if lo_open else '['}{lo:g}"
            right = "inf)" if hi is None else f"{hi:g}{')' if hi_open else ']'}"
            _fail(f"must lie in {left}, {right}, got {text!r}")
        return value
    parse.__name__ = "float_range"
    return parse


#: An integer ≥ 1.
positive_int = int_range(1)
#: An integer ≥ 0.
nonnegative_int = int_range(0)
#: A finite number > 0.
positive_float = float_range(0.0)
#: A length in metres the stages can resolve: from :data:`MIN_LENGTH` to :data:`MAX_LENGTH` (a
#: longer one overflows the float32 bounds of a model's octree).
length = float_range(MIN_LENGTH, MAX_LENGTH, lo_open=False)
#: A finite number ≥ 0.
nonnegative_float = float_range(0.0, lo_open=False)
#: A finite number.
finite_float = float_range()
#: A step along a path (m): at least a centimetre, so that a walk's poses stay countable.
MIN_STEP = 0.01
#: Street lengths of bench's city runs, in multiples of --street-length.
MAX_CITY_SCALE = 64


def zero_or_at_least(lo: float):
    """An argparse type: 0, or a finite number ≥ lo."""
    at_least = float_range(lo, lo_open=False)

    def parse(text: str) -> float:
        value = _parse_float(text)
        return 0.0 if value == 0 else at_least(text)
    parse.__name__ = "zero_or_at_least"
    return parse


#: A GPU memory budget in MB: more than 0, at most a petabyte (its bytes stay an exact integer).
gpu_budget_mb = float_range(0.0, 1e9)
#: A size edge in pixels or texels: an integer in [1, GL_MAX_SIZE].
dimension = int_range(1, GL_MAX_SIZE, "the OpenGL texture and renderbuffer limit")


def holdout(text: str) -> int:
    """An argparse type: every n-th frame held out, 0 (none) or ≥ 2."""
    value = _parse_int(text)
    if value < 0 or value == 1:
        _fail(f"must be 0 (none) or at least 2 (every n-th frame), got {value}")
    return value


def max_workers() -> int:
    """The most parallel processes a command may start: 4 × the usable cores."""
    from .executor import default_workers

    return 4 * default_workers()


def worker_count(text: str) -> int:
    """An argparse type: parallel processes, an integer in [1, :func:`max_workers`]."""
    return int_range(1, max_workers(), "4 × the usable cores")(text)


#: A Dask scheduler address: [scheme://]host:port, the host a name, an IPv4 address or a
#: bracketed IPv6 address.
_SCHEDULER_ADDRESS = re.compile(r"^(?:(?P<scheme>[a-z]+)://)?(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9._-]+)"
                                r":(?P<port>[0-9]+)$")

#: Transports a Dask scheduler listens on.
SCHEDULER_SCHEMES = ("tcp", "tls", "ws", "wss", "ucx")


def scheduler_address(text: str) -> str:
    """An argparse type: the address of a running Dask scheduler, ``tcp://host:8786`` (the
    transport optional, tcp by default; the port required, so that a stray word is no host)."""
    m = _SCHEDULER_ADDRESS.match(text.strip())
    if m is None:
        _fail(f"expected a scheduler address such as tcp://host:8786, got {text!r}")
    if m["scheme"] is not None and m["scheme"] not in SCHEDULER_SCHEMES:
        _fail(f"unknown transport {m['scheme']!r}; choose from {', '.join(SCHEDULER_SCHEMES)}")
    if not 1 <= int(m["port"]) <= 65535:
        _fail(f"port must lie in [1, 65535], got {m['port']}")
    return text.strip()


def available_memory() -> int | None:
    """Bytes a new allocation can get: MemAvailable of /proc/meminfo, else the free
    physical pages (os.sysconf); None where neither is known."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024  # kB
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, OSError, ValueError):
        return None


def check_memory(nbytes: float, what: str) -> None:
    """UsageError naming ``what`` when ``nbytes`` exceeds the available memory (nothing
    when that is unknown)."""
    available = available_memory()
    if available is not None and nbytes > available:
        raise UsageError(f"{what} needs about {nbytes / 2**30:.1f} GiB of memory, more than the "
                         f"{available / 2**30:.1f} GiB available")


def size_action(bytes_per_pixel: int):
    """An argparse action for ``--size W H`` (parsed with ``type=dimension``): refuses a size
    whose W·H·bytes_per_pixel exceeds the available memory."""
    class SizeAction(argparse.Action):
        def __call__(self, parser, namespace, values, option_string=None):
            w, h = values
            try:
                check_memory(w * h * bytes_per_pixel, f"{w}x{h}")
            except InputError as e:
                raise argparse.ArgumentError(self, str(e)) from None
            setattr(namespace, self.dest, tuple(values))
    return SizeAction


def synth_bytes(width: int, height: int, spp: int, distorted: bool, workers: int) -> int:
    """Bytes ``synth`` holds at once: per worker one image's uint8 RGB, float32 depth and
    int32 ids and its PNG encoding (about 14 B/pixel), a lens's (1 + spp²) float64
    undistorted ray coordinates per pixel, and a row chunk of rays (about 100 B per ray)."""
    pixels = width * height
    per_image = pixels * 14 + (pixels * (1 + spp * spp) * 16 if distorted else 0) + width * spp * spp * 100
    return workers * per_image


def build_bytes(tile: int, directions: int, chunk: int, workers: int, fit_quads: int = 0) -> int:
    """Bytes the build's workers hold at once: each a chunk of billboards' sampled textures
    (directions × tile² × 4 channels) at BUILD_BYTES_PER_TEXEL, or with a fit the larger of that
    and the solve of ``fit_quads`` billboards (FIT_BYTES_PER_UNKNOWN per colour of a texel)."""
    sampled = chunk * directions * tile * tile * 4 * BUILD_BYTES_PER_TEXEL
    return workers * max(sampled, fit_quads * directions * tile * tile * 3 * FIT_BYTES_PER_UNKNOWN)


class CommandParser(argparse.ArgumentParser):
    """A subcommand's parser that also runs its ``check_options`` default on the parsed options:
    a function of the namespace raising :class:`~core.errors.InputError` for a combination of
    values (a tile larger than the atlas page, a size the memory cannot hold), reported like any
    other bad option (a usage line, exit 2) before the command starts.

    A description is one paragraph, written as prose across lines of the source: its runs of
    whitespace are single spaces, as the help prints it."""

    def __init__(self, *args, description: str | None = None, **kwargs):
        super().__init__(*args, description=None if description is None else " ".join(description.split()), **kwargs)

    def parse_known_args(self, args=None, namespace=None):
        namespace, extras = super().parse_known_args(args, namespace)
        check = getattr(namespace, "check_options", None)
        if check is not None:
            try:
                check(namespace)
            except InputError as e:
                self.error(str(e))
        return namespace, extras
