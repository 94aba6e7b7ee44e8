"""The one point-mass lattice filter (`neuralmap.filters.lattice.filter.LatticeFilter`: the
state, the measurement update and the moments) with its lattice rule as an object: the
fixed / adaptive grid of acquisition (`neuralmap.filters.lattice.grid_rule.GridLattice`;
configuration `neuralmap.filters.point_mass.PointMassFilter`) or the lattice that follows
the posterior (`neuralmap.filters.lattice.follow_rule.FollowLattice`; configuration
`neuralmap.filters.point_mass_tracker.PointMassTracker`), all on one set of kernels
(`neuralmap.filters.lattice.kernels`: prediction by separable convolution, the log-domain
Rao-Blackwellised update, bilinear regrid and lattice moments). The following lattice's
step as static-shape functions (eager, or under ``torch.compile``) is
`neuralmap.filters.lattice.follow_step`; the same algorithm in NumPy, one run at a time,
is `neuralmap.filters.lattice.reference`; rules by name: `neuralmap.filters.lattice.rule`."""

from neuralmap.filters.lattice.filter import LatticeFilter, LatticeUpdate
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
from neuralmap.filters.lattice.rule import LATTICE_RULES, make_lattice_filter

__all__ = ["LATTICE_RULES", "LatticeFilter", "LatticeMoments", "LatticeUpdate",
           "WeightUpdate", "affine_field", "blur", "cell_log_likelihood", "conditional_mean",
           "convolve_axis", "gaussian_kernels", "gaussian_log_density", "kalman_cells",
           "make_lattice_filter", "mass_moments", "normalised", "resample_bilinear",
           "toeplitz_kernels", "weight_update"]
