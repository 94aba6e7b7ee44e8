"""Differentiable TAN: learn the noise model and refine the map from flights, through the filter.

* :mod:`~neuralmap.learning.covariance`: positive-definite parametrisations (log-diagonal,
  log-Cholesky).
* :mod:`~neuralmap.learning.flights`: padded, masked flight batches.
* :mod:`~neuralmap.learning.flight_log`: the CSV/NPZ flight-log format and its reader.
* :mod:`~neuralmap.learning.likelihood`: the innovation log-likelihood through the filter.
* :mod:`~neuralmap.learning.noise_model`, :mod:`~neuralmap.learning.noise_fit`: learning Q, R.
* :mod:`~neuralmap.learning.em`: the Shumway–Stoffer EM reference for linear models.
* :mod:`~neuralmap.learning.map_correction`: the learnable correction grid, a biased map.
* :mod:`~neuralmap.learning.map_refine`: refining the map from altimeter residuals.
"""
