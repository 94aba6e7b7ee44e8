"""The point-mass lattice filter's one set of kernels (`neuralmap.filters.lattice.kernels`):
prediction by separable convolution, the log-domain Rao-Blackwellised measurement update,
bilinear regrid and lattice moments. Both lattice policies — the fixed / adaptive grid of
acquisition (`neuralmap.filters.point_mass.PointMassFilter`) and the lattice that follows
the posterior (`neuralmap.filters.point_mass_tracker.PointMassTracker`) — run on them."""

from neuralmap.filters.lattice.kernels import (
    LatticeMoments,
    WeightUpdate,
    affine_field,
    blur,
    cell_log_likelihood,
    conditional_mean,
    convolve_axis,
    gaussian_kernels,
    gaussian_log_density,
    kalman_cells,
    mass_moments,
    normalised,
    resample_bilinear,
    toeplitz_kernels,
    weight_update,
)

__all__ = ["LatticeMoments", "WeightUpdate", "affine_field", "blur", "cell_log_likelihood",
           "conditional_mean", "convolve_axis", "gaussian_kernels", "gaussian_log_density",
           "kalman_cells", "mass_moments", "normalised", "resample_bilinear",
           "toeplitz_kernels", "weight_update"]
