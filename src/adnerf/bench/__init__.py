"""Benchmarks: error against run time (``adnerf bench ...``).

- :mod:`~adnerf.bench.render`: quadrature error of the renderer on an analytic sphere, and the
  audio features' speed.
- :mod:`~adnerf.bench.fields`: held-out PSNR against training time, per field configuration.
- :mod:`~adnerf.bench.real`: a real clip end to end (preprocess, train, held-out metrics).
- :mod:`~adnerf.bench.voices`: the synthetic head driven by voices it was not trained on.
"""
