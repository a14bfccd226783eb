"""moderngl renderer, culling and viewer (built by a later issue)."""
