"""A billboard model as one binary glTF 2.0 file (.glb): every quad a fixed, textured alpha quad.

What is written (:func:`export_gltf`):

* **Geometry.** Every quad of the model is a square of 4 vertices and 2 triangles, placed exactly
  as ``render/shaders/billboard_quad.glsl`` places it (:func:`quad_corners`, from
  :func:`billboards.geometry.kind_frames`): facade blocks vertical and ground blocks flat at their
  base yaw, ground blocks GROUND_OVERLAP of their edge larger and their corners lifted by the
  height field (``corner_dz``, bilinear in the block's world x and y), the triangles split along
  the renderer's strip diagonal (corner (1,0)–(0,1)). A billboard turns toward the eye in the
  renderer; here it stays where the renderer draws it for an eye level with it at its base yaw
  (the yaw from the voxel toward the capture path): it faces the path.
* **Textures.** Each quad shows one decoded texture (:func:`billboards.decode.decode`): the
  sampled direction nearest to looking straight at the quad (yaw offset and pitch nearest 0,
  ties toward the upper index as the renderer's nearest-direction mode; for a layer block the
  capture direction nearest the street's normal) or, with ``texture="mean"``, its mean tile. The
  t×t tiles are packed into atlas images of at most ``max_image``² texels (:func:`pack_atlas`),
  each tile surrounded by a gutter of its own border texels: bilinear filtering then never reads
  a neighbouring tile, and a ground block's overlap repeats its border texels as the renderer's
  clamp does (the gutter is wide enough for it). Texel row 0 is the top of a quad (glTF's image
  origin is its top-left corner). Images are PNG; one unlit material per image
  (KHR_materials_unlit, alphaMode MASK at 0.5 as the renderer's discard, double-sided), one
  primitive per material.
* **Axes.** glTF is y-up: world (x, y, z) (z up, metres) is glTF (x, z, −y), a rotation. Vertex
  positions are float32 relative to the model's origin; the root node's translation is the
  origin in glTF axes (float64 in the JSON), and ``asset.extras.bbcity`` records the world origin.
"""

from __future__ import annotations

import errno
import io
import math
import os
import struct
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pygltflib
from PIL import Image

from billboards.atlas import read_tiles
from billboards.decode import decode
from billboards.geometry import GROUND, GROUND_OVERLAP, kind_frames, surface_dz
from billboards.model import BillboardModel
from billboards.model_reader import load
from core.errors import InputError
from core.fileio import atomic_path

TEXTURES = ("direction", "mean")
UNLIT = "KHR_materials_unlit"
#: glTF (x, y, z) = world (x, z, −y): rows map world vectors to glTF vectors (a rotation).
GLTF_FROM_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
#: the strip's corners (0,0), (1,0), (0,1), (1,1) along (right, up), and its two triangles
CORNERS = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
TRIANGLES = np.array([0, 1, 2, 2, 1, 3], np.uint32)


@dataclass(frozen=True)
class GltfConfig:
    texture: str = "direction"   # "direction": the sampled direction looking straight at each quad; "mean": its mean tile
    max_image: int = 8192        # largest atlas image edge (texels); more quads make more images and materials
    ground_overlap: bool = True  # ground blocks GROUND_OVERLAP larger, as drawn; False: their exact squares (shared corners)
    chunk: int = 16384           # quads decoded at once (bounds the float32 temporaries)
    png_level: int = 6           # zlib level of the PNG images, 0 (fastest) to 9 (smallest)

    def __post_init__(self):
        if self.texture not in TEXTURES:
            raise InputError(f"texture must be one of {list(TEXTURES)}, got {self.texture!r}")
        for name, lo, hi in (("max_image", 16, 1 << 16), ("chunk", 1, 1 << 24), ("png_level", 0, 9)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
                raise InputError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
        if not isinstance(self.ground_overlap, bool):
            raise InputError(f"ground_overlap must be true or false, got {self.ground_overlap!r}")


def quad_corners(centres: np.ndarray, kind: np.ndarray, base_yaw: np.ndarray, edges: np.ndarray,
                 corner_dz: np.ndarray, overlap: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The renderer's quad corners with every quad facing its base yaw, level (pitch 0).

    centres (n, 3) float (m, model coordinates), kind (n,) uint8, base_yaw (n,) float radians,
    edges (n,) float (m), corner_dz (n, 4) float (m) → positions (n, 4, 3) float64 (model
    coordinates, corners (0,0), (1,0), (0,1), (1,1) along right and up) and params (n, 4, 2)
    float64 the corners' (right, up) fractions, −GROUND_OVERLAP … 1 + GROUND_OVERLAP for ground
    blocks with ``overlap``, else 0 … 1 (tile coordinate: col = x·t, row = (1 − y)·t).
    """
    centres = np.asarray(centres, np.float64).reshape(-1, 3)
    kind = np.asarray(kind).reshape(-1)
    yaw = np.asarray(base_yaw, np.float64).reshape(-1)
    size = np.asarray(edges, np.float64).reshape(-1, 1, 1)
    _, right, up = kind_frames(kind, yaw, yaw, np.zeros_like(yaw))
    grow = np.where((kind == GROUND) & overlap, 1.0 + 2.0 * GROUND_OVERLAP, 1.0)
    params = (CORNERS[None] - 0.5) * grow[:, None, None] + 0.5                      # (n, 4, 2)
    offset = (params[..., :1] - 0.5) * right[:, None] + (params[..., 1:] - 0.5) * up[:, None]
    points = centres[:, None, :] + size * offset
    f = offset[..., :2] + 0.5   # the world x and y fractions of the block: (p.xy − centre.xy)/s + ½
    points[..., 2] += surface_dz(np.asarray(corner_dz, np.float64).reshape(-1, 1, 4), f[..., 0], f[..., 1])
    return points, params


def facing_direction(model: BillboardModel) -> tuple[int, int]:
    """(yaw index, pitch index) of the sampled direction nearest yaw offset 0 and pitch 0 (ties up)."""
    yi = np.interp(0.0, model.yaw_offsets, np.arange(len(model.yaw_offsets), dtype=np.float64))
    pi = np.interp(0.0, model.pitches, np.arange(len(model.pitches), dtype=np.float64))
    return int(np.floor(yi + 0.5)), int(np.floor(pi + 0.5))


def quad_textures(model: BillboardModel, texture: str = "direction", chunk: int = 16384) -> np.ndarray:
    """Every quad's texture as exported: (n, t, t, 4) uint8 RGBA = round(255 · value), value the
    CPU decode at :func:`facing_direction` (``texture="direction"``) or the dequantised mean tile
    offset + scale·q clipped to [0, 1] (``"mean"``); row 0 is the quad's top."""
    n, t = model.num_billboards, model.tile
    out = np.empty((n, t, t, 4), np.uint8)
    yi, pi = facing_direction(model)
    for s in range(0, n, chunk):
        b = np.arange(s, min(s + chunk, n))
        if texture == "mean":
            slots = model.first_slot[b].astype(np.int64)
            q = read_tiles(model.pages, slots, t, model.page_size).astype(np.float32)
            if model.tile_mode == "u8":
                q /= np.float32(255)
            tex = np.clip(model.slot_offset[slots][:, None, None] + model.slot_scale[slots][:, None, None] * q, 0, 1)
        else:
            tex = decode(model, b, float(yi), float(pi))
        out[b] = np.rint(tex * 255)
    return out


def gutter_width(tile: int, ground: bool) -> int:
    """Texels of border repeated around each tile: 1, or enough that a ground block's overlap
    (GROUND_OVERLAP·t beyond its tile) stays in texels equal to the border under bilinear filtering."""
    return max(1, math.ceil(GROUND_OVERLAP * tile + 0.5)) if ground else 1


def pack_atlas(tiles: np.ndarray, gutter: int, max_image: int) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Pack tiles (n, t, t, 4) uint8 with ``gutter`` texels of their own border around each into
    images of at most ``max_image``² texels, each about square.

    Returns images [(H, W, 4) uint8], image (n,) int64 the image of each tile and xy (n, 2)
    float64 the texel position of each tile's top-left corner (inside the gutter) in its image.
    """
    n, t = len(tiles), tiles.shape[1]
    cell = t + 2 * gutter
    side = max_image // cell
    if side < 1:
        raise InputError(f"a tile of {t} texels with its gutter ({cell}) does not fit an image of {max_image}")
    per_image = side * side
    images, image, xy = [], np.zeros(n, np.int64), np.zeros((n, 2), np.float64)
    for k, s in enumerate(range(0, n, per_image)):
        m = min(per_image, n - s)
        cols = min(side, math.ceil(math.sqrt(m)))
        rows = math.ceil(m / cols)
        cells = np.zeros((rows * cols, cell, cell, 4), np.uint8)
        cells[:m] = np.pad(tiles[s:s + m], ((0, 0), (gutter, gutter), (gutter, gutter), (0, 0)), mode="edge")
        images.append(cells.reshape(rows, cols, cell, cell, 4).transpose(0, 2, 1, 3, 4).reshape(rows * cell, cols * cell, 4))
        i = np.arange(m)
        image[s:s + m] = k
        xy[s:s + m, 0] = (i % cols) * cell + gutter
        xy[s:s + m, 1] = (i // cols) * cell + gutter
    return images, image, xy


def _png(image: np.ndarray, level: int) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(image, "RGBA").save(buf, format="PNG", compress_level=level)
    return buf.getvalue()


class _Blob:
    """The GLB's binary chunk: byte views appended 4-byte aligned, with accessors over them."""

    def __init__(self, gltf: pygltflib.GLTF2):
        self.gltf, self.parts, self.size = gltf, [], 0

    def view(self, data: bytes, target: int | None = None) -> int:
        self.gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=self.size, byteLength=len(data),
                                                          target=target))
        pad = (-len(data)) % 4
        self.parts.append(data + b"\0" * pad)
        self.size += len(data) + pad
        return len(self.gltf.bufferViews) - 1

    def accessor(self, array: np.ndarray, kind: str, target: int, bounds: bool = False) -> int:
        component = {np.dtype(np.float32): pygltflib.FLOAT, np.dtype(np.uint32): pygltflib.UNSIGNED_INT}[array.dtype]
        extra = {"min": array.min(0).tolist(), "max": array.max(0).tolist()} if bounds else {}
        self.gltf.accessors.append(pygltflib.Accessor(
            bufferView=self.view(np.ascontiguousarray(array).tobytes(), target), componentType=component,
            count=len(array), type=kind, **extra))
        return len(self.gltf.accessors) - 1


def check_output(out_path: os.PathLike | str) -> Path:
    """``out_path`` as a Path, refused when it exists (FileExistsError) or its directory does not
    (FileNotFoundError), both naming it."""
    out = Path(out_path)
    if out.exists() or out.is_symlink():
        raise FileExistsError(errno.EEXIST, "already exists; not replacing it", str(out))
    if not out.parent.is_dir():
        raise FileNotFoundError(errno.ENOENT, "the output's directory does not exist", str(out))
    return out


def model_glb(model: BillboardModel, config: GltfConfig = GltfConfig()) -> tuple[bytes, dict]:
    """The GLB of ``model`` (see the module's docstring) and a report: quads, vertices, images,
    texture size (texels of all images), gutter, world bounds lo/hi (3,) of the written vertices."""
    n, t = model.num_billboards, model.tile
    origin = np.asarray(model.origin, np.float64)
    gltf = pygltflib.GLTF2(asset=pygltflib.Asset(version="2.0", generator="bbcity share.gltf", extras={"bbcity": {
        "world_origin": origin.tolist(), "axes": "glTF (x, y, z) = world (x, z, -y), metres; world z is up",
        "quads": n, "texture": config.texture, "source": {"format": "bbcity-billboards", "tile": t}}}))
    root = pygltflib.Node(name="model", translation=(GLTF_FROM_WORLD @ origin).tolist())
    gltf.nodes.append(root)
    gltf.scenes.append(pygltflib.Scene(nodes=[0]))
    gltf.scene = 0
    report = {"quads": n, "vertices": 4 * n, "images": 0, "texture_texels": 0, "tile": t, "gutter": 0,
              "world_lo": origin.tolist(), "world_hi": origin.tolist()}
    if n == 0:   # a GLB of its JSON chunk only (an empty BIN chunk or buffer is not allowed)
        text = gltf.to_json(separators=(",", ":")).encode()
        text += b" " * ((-len(text)) % 4)
        head = struct.pack("<4sII", b"glTF", 2, 20 + len(text)) + struct.pack("<I4s", len(text), b"JSON")
        return head + text, report

    corners, params = quad_corners(model.centres, model.kind, model.base_yaw, model.edges(), model.corner_dz,
                                   config.ground_overlap)
    local = corners.reshape(-1, 3).astype(np.float32)
    gutter = gutter_width(t, config.ground_overlap and bool(np.any(model.kind == GROUND)))
    images, image, xy = pack_atlas(quad_textures(model, config.texture, config.chunk), gutter, config.max_image)
    texel = xy[:, None, :] + np.stack([params[..., 0], 1.0 - params[..., 1]], axis=-1) * t   # (n, 4, 2)

    blob = _Blob(gltf)
    gltf.extensionsUsed = [UNLIT]
    gltf.samplers.append(pygltflib.Sampler(magFilter=pygltflib.LINEAR, minFilter=pygltflib.LINEAR,
                                           wrapS=pygltflib.CLAMP_TO_EDGE, wrapT=pygltflib.CLAMP_TO_EDGE))
    primitives = []
    for k, img in enumerate(images):
        sel = np.flatnonzero(image == k)
        uv = (texel[sel] / np.array([img.shape[1], img.shape[0]], np.float64)).reshape(-1, 2).astype(np.float32)
        pos = np.ascontiguousarray(local.reshape(n, 4, 3)[sel].reshape(-1, 3) @ GLTF_FROM_WORLD.T.astype(np.float32))
        idx = (np.arange(len(sel), dtype=np.uint32)[:, None] * 4 + TRIANGLES[None]).reshape(-1)
        gltf.images.append(pygltflib.Image(bufferView=blob.view(_png(img, config.png_level)), mimeType="image/png"))
        gltf.textures.append(pygltflib.Texture(sampler=0, source=k))
        gltf.materials.append(pygltflib.Material(
            name=f"atlas_{k}", pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
                baseColorTexture=pygltflib.TextureInfo(index=k), metallicFactor=0.0, roughnessFactor=1.0),
            alphaMode=pygltflib.MASK, alphaCutoff=0.5, doubleSided=True, extensions={UNLIT: {}}))
        primitives.append(pygltflib.Primitive(
            attributes=pygltflib.Attributes(POSITION=blob.accessor(pos, pygltflib.VEC3, pygltflib.ARRAY_BUFFER, True),
                                            TEXCOORD_0=blob.accessor(uv, pygltflib.VEC2, pygltflib.ARRAY_BUFFER)),
            indices=blob.accessor(idx, pygltflib.SCALAR, pygltflib.ELEMENT_ARRAY_BUFFER), material=k,
            mode=pygltflib.TRIANGLES))
    gltf.meshes.append(pygltflib.Mesh(name="quads", primitives=primitives))
    root.mesh = 0
    data = b"".join(blob.parts)
    gltf.buffers.append(pygltflib.Buffer(byteLength=len(data)))
    gltf.set_binary_blob(data)
    world = origin + local.astype(np.float64)
    report.update(images=len(images), texture_texels=int(sum(i.shape[0] * i.shape[1] for i in images)),
                  gutter=gutter, image_sizes=[[int(i.shape[1]), int(i.shape[0])] for i in images],
                  world_lo=world.min(0).tolist(), world_hi=world.max(0).tolist())
    return b"".join(gltf.save_to_bytes()), report


def write_glb(model: BillboardModel, out_path: os.PathLike | str, config: GltfConfig = GltfConfig()) -> dict:
    """Write :func:`model_glb` of ``model`` to ``out_path`` atomically (a temporary file beside it,
    renamed); returns its report with the bytes written. No check of ``out_path`` here."""
    data, report = model_glb(model, config)
    with atomic_path(out_path) as tmp:
        tmp.write_bytes(data)
    report["bytes"] = len(data)
    return report


def export_gltf(model_dir: os.PathLike | str, out_path: os.PathLike | str, config: GltfConfig = GltfConfig()) -> dict:
    """Export the model directory ``model_dir`` as the binary glTF ``out_path`` (.glb).

    Refuses an existing ``out_path`` (FileExistsError) or one whose directory is missing
    (FileNotFoundError); a directory that is no model raises the reader's DataFormatError naming
    its file. Returns a report: quads, vertices, images, texture_texels, tile, gutter, world
    bounds, bytes, seconds.
    """
    start = time.perf_counter()
    out = check_output(out_path)
    if out.suffix.lower() != ".glb":
        raise InputError(f"{out}: a binary glTF file's name ends in .glb")
    model = load(model_dir, mmap=True)
    report = write_glb(model, out, config)
    report["seconds"] = time.perf_counter() - start
    return report
