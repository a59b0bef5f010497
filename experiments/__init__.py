"""Benchmarks, figures and sweeps on top of the library; run each from the project root as
`python -m experiments.NAME` (their extra needs: `pip install -e ".[experiments]"`)."""
