"""Layer 0, what every layer stands on: host-boundary checks (`_checks`), small dense algebra
on simplices (`_simplex`), device meshes (`_sharding`) and progress bars (`_progress`).
Imports nothing from jaxgeom. The public names live in `jaxgeom/__init__.py`."""
