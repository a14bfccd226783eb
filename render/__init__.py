"""moderngl renderer of billboard models: cameras, GPU resources, GPU and CPU decode, offscreen.

The only package that imports moderngl. Public entry points:

- :func:`render.offscreen.render_view` — one call, (h, w, 3) uint8 image;
- :class:`render.renderer.BillboardRenderer` — a model on a context, ``render()`` per frame;
- :func:`render.context.create_context` — headless (EGL) standalone context.
"""
