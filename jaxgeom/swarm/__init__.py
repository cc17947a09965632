"""Layer 3, the swarm: dynamics and observables, the graph lifecycle, initialisation, the
drivers of `simulate`, and tuning through whole simulations. Imports from the layers below
only. The public names live in `jaxgeom/__init__.py`."""
