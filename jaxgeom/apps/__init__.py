"""Layer 4, applications of the library: the built-in fitness landscapes (`_landscapes`),
estimator validation on them (`_validation`) and figures (`_plots`). The command line sits
above, in `jaxgeom/cli/`. The public names live in `jaxgeom/__init__.py`."""
