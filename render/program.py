"""Shader programs from ``render/shaders/*.glsl`` (package data).

One file per program, in the style of moderngl-window: the file starts with a
``#version`` line and holds every stage, each inside ``#if defined VERTEX_SHADER``
/ ``#elif defined FRAGMENT_SHADER`` … ``#endif``. :func:`load_program` compiles the
file once per stage with the matching ``#define`` injected after ``#version``.

A line ``#include "name.glsl"`` is replaced by that file from the same folder
(recursively), so programs that must agree exactly (the GPU and CPU decode paths
build the same quads) share one source of that code.
"""

from __future__ import annotations

import functools
import re
from importlib import resources

import moderngl

STAGES = ("VERTEX_SHADER", "FRAGMENT_SHADER", "GEOMETRY_SHADER")
_INCLUDE = re.compile(r'^\s*#include\s+"([A-Za-z0-9_.\-]+)"\s*$')
_MAX_DEPTH = 16


class ShaderError(RuntimeError):
    """A shader file is missing, malformed or does not compile (the message names the file)."""


@functools.lru_cache(maxsize=None)
def shader_source(name: str) -> str:
    """Text of ``render/shaders/<name>`` with ``#include`` lines resolved."""
    return _resolve(name, 0)


def _read(name: str) -> str:
    path = resources.files("render").joinpath("shaders", name)
    try:
        return path.read_text(encoding="utf-8")
    except (FileNotFoundError, IsADirectoryError):
        raise ShaderError(f"shader file render/shaders/{name} not found") from None


def _resolve(name: str, depth: int) -> str:
    if depth > _MAX_DEPTH:
        raise ShaderError(f"render/shaders/{name}: #include nested deeper than {_MAX_DEPTH} (a cycle?)")
    out = []
    for line in _read(name).splitlines():
        m = _INCLUDE.match(line)
        out.append(_resolve(m.group(1), depth + 1) if m else line)
    return "\n".join(out)


def stage_sources(name: str, defines: dict[str, object] | None = None) -> dict[str, str]:
    """Per-stage sources of a program file: ``{"vertex_shader": …, "fragment_shader": …}``.

    Only the stages whose ``#if defined <STAGE>`` appears in the file are returned;
    ``defines`` become ``#define KEY VALUE`` lines after ``#version``.
    """
    text = shader_source(name).strip()
    lines = text.splitlines()
    if not lines or not lines[0].startswith("#version"):
        raise ShaderError(f"render/shaders/{name}: the first line must be #version")
    extra = [f"#define {k} {v}" for k, v in (defines or {}).items()]
    out = {}
    for stage in STAGES:
        if re.search(rf"defined\s*\(?\s*{stage}\b", text):
            body = [lines[0], f"#define {stage} 1", *extra, "#line 2", *lines[1:]]
            out[stage.lower()] = "\n".join(body) + "\n"
    if "vertex_shader" not in out:
        raise ShaderError(f"render/shaders/{name}: no VERTEX_SHADER section")
    return out


#: What a GLSL ES 3.00 (WebGL2) stage starts with instead of ``#version 330 core``: ES has no
#: default precision for floats in fragment shaders nor for samplers of arrays.
ES_HEADER = ("#version 300 es", "precision highp float;", "precision highp int;",
             "precision highp sampler2D;", "precision highp sampler2DArray;")


def es_stage_sources(name: str, defines: dict[str, object] | None = None) -> dict[str, str]:
    """:func:`stage_sources` of ``render/shaders/<name>`` for WebGL2: the same text (the web viewer
    decodes and draws with the desktop's shaders) under :data:`ES_HEADER`."""
    out = {}
    for stage, text in stage_sources(name, defines).items():
        out[stage] = "\n".join(ES_HEADER) + "\n" + text.split("\n", 1)[1]
    return out


def load_program(ctx: moderngl.Context, name: str, defines: dict[str, object] | None = None) -> moderngl.Program:
    """Compile and link ``render/shaders/<name>``; ShaderError names the file on failure."""
    try:
        return ctx.program(**stage_sources(name, defines))
    except moderngl.Error as e:
        raise ShaderError(f"render/shaders/{name}: {e}") from None


class ProgramCache:
    """Programs compiled once per (file, defines) and shared by every pass drawn with them.

    Compiling and linking costs tens of milliseconds on llvmpipe, so the renderers of a tiled
    model (one per resident tile) share one cache instead of compiling their own on upload.
    Sharing is sound because every pass sets all the uniforms it uses before each draw. The
    cache owns its programs: :meth:`release` frees them (idempotent); the passes do not.
    """

    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self._programs: dict[tuple, moderngl.Program] | None = {}

    def get(self, name: str, defines: dict[str, object] | None = None) -> moderngl.Program:
        """The program of ``render/shaders/<name>`` with ``defines``, compiled on first use."""
        if self._programs is None:
            raise RuntimeError("ProgramCache used after release()")
        key = (name, tuple(sorted((defines or {}).items())))
        program = self._programs.get(key)
        if program is None:
            program = self._programs[key] = load_program(self.ctx, name, defines)
        return program

    def __len__(self) -> int:
        return len(self._programs or {})

    def release(self) -> None:
        for program in (self._programs or {}).values():
            program.release()
        self._programs = None
