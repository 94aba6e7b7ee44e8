"""Differentiable TAN: learn the noise model and refine the map from flights, through the filter.

* `covariance`: positive-definite parametrisations (log-diagonal,
  log-Cholesky).
* `flights`: padded, masked flight batches.
* `flight_log`: the CSV/NPZ flight-log format and its reader.
* `likelihood`: the innovation log-likelihood through the filter.
* `noise_model`, `noise_fit`: learning Q, R.
* `em`: the Shumway–Stoffer EM reference for linear models.
* `map_correction`: the learnable correction grid, a biased map.
* `map_refine`: refining the map from altimeter residuals.
"""
