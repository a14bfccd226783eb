"""OpenGL contexts: headless (EGL) standalone contexts and their limits.

On a machine without a display, ``moderngl.create_standalone_context(backend="egl")``
gives a context on the GPU's EGL driver or, without a GPU, on Mesa's llvmpipe
(software, OpenGL 4.5). :func:`create_context` tries EGL first and falls back to
the platform default (GLX/WGL/CGL), so the same code runs on a desktop.
"""

from __future__ import annotations

import logging

import moderngl

logger = logging.getLogger(__name__)

#: GLSL/OpenGL version the shaders need (texelFetch on array textures, flat ints, gl_VertexID).
REQUIRED_GL = 330


class ContextError(RuntimeError):
    """No OpenGL context of the required version could be created."""


def create_context(require: int = REQUIRED_GL, backend: str | None = "egl") -> moderngl.Context:
    """A standalone (offscreen) moderngl context of at least OpenGL ``require`` (330 = 3.3).

    ``backend="egl"`` (headless) is tried first; if it fails, the platform default
    backend is tried. ``backend=None`` asks for the default only. Raises
    :class:`ContextError` listing each attempt's error when none works.
    """
    attempts = ([backend] if backend else []) + [None]
    errors = []
    for b in attempts:
        try:
            ctx = (moderngl.create_standalone_context(require=require, backend=b) if b
                   else moderngl.create_standalone_context(require=require))
        except Exception as e:  # moderngl raises plain Exception subclasses per backend
            errors.append(f"{b or 'default'}: {e}")
            continue
        if ctx.version_code < require:
            errors.append(f"{b or 'default'}: OpenGL {ctx.version_code} < {require}")
            ctx.release()
            continue
        if errors:
            logger.info("EGL context unavailable (%s); using the default backend", "; ".join(errors))
        logger.debug("OpenGL context: %s", describe(ctx))
        return ctx
    raise ContextError("no OpenGL context of version ≥ %d: %s" % (require, "; ".join(errors)))


def max_texture_size(ctx: moderngl.Context) -> int:
    """GL_MAX_TEXTURE_SIZE: the largest texture edge in texels (8192 or 16384 on most GPUs)."""
    return int(ctx.info["GL_MAX_TEXTURE_SIZE"])


def max_array_layers(ctx: moderngl.Context) -> int:
    """GL_MAX_ARRAY_TEXTURE_LAYERS: the most layers of a texture array."""
    return int(ctx.info["GL_MAX_ARRAY_TEXTURE_LAYERS"])


def describe(ctx: moderngl.Context) -> str:
    """One line: renderer, vendor and version (for logs and benchmark reports)."""
    info = ctx.info
    return f"{info['GL_RENDERER']} ({info['GL_VENDOR']}), OpenGL {info['GL_VERSION']}"


def is_software(ctx: moderngl.Context) -> bool:
    """True on a software rasteriser (llvmpipe, softpipe, SwiftShader)."""
    name = str(ctx.info["GL_RENDERER"]).lower()
    return any(s in name for s in ("llvmpipe", "softpipe", "swiftshader", "software"))
