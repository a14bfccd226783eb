"""Sharing a model outside bbcity: a static web viewer site, glTF and 3D Tiles exports."""
