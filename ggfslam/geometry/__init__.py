"""Geometry helpers: SE(3), depth back-projection, normals."""
