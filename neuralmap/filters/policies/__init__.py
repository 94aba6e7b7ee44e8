"""Robust and adaptive update policies for `BatchedEKF`.

Pass one as ``ekf.update(residual, H, R, policy=...)`` (and ``ekf.predict(F, Q,
policy=...)`` for the ones adapting Q). Families (one module each):

* robust weights: `IGG3` (SEEDS 002), `Huber`, `ChiSquareGate`;
* adaptive factors on ``P⁻``: `YangAdaptive` (SEEDS 002),
  `InnovationInflation` (SEEDS 003, the literal single-epoch form) and
  `WindowedInflation` (SEEDS 003 with a window of innovations, on a state block);
* their composition `RobustAdaptive` (SEEDS 002's RAF) and `Compose`;
* noise estimation: `SageHusa` (SEEDS 002), `QualityR` (SEEDS 003),
  `VariationalAdaptive` (Huang et al., IEEE TAC 2018).

Configs, studies and benchmarks build policies by name through `make_policy`
(`POLICIES`: name → label, builder and the papers' defaults), e.g.
``make_policy("raf")`` or ``make_policy("sage_husa", {"R_min": 1.0, "R_max": 1e4})``.

The pure weight/factor functions (batched tensors in, tensors out) are exported too.

Every policy reports per sample what it did in ``UpdateDiagnostics.policy_info``
(weights, factors, adapted variances); a policy with per-sample state (Sage-Husa, the
variational filter) belongs to one filter: call ``reset()`` before a new batch.

Example::

    raf = RobustAdaptive(k0=1.5, k1=4.5, c0=1.5, c1=8.5)    # = make_policy("raf")
    diag = ekf.update(residual, H, R, policy=raf)       # diag.policy_info["yang.alpha"]

    quality = QualityR.altimeter()
    tuned = Compose(quality, InnovationInflation(c0=1.2))  # paper 003: R first, then α
    quality.set_quality(indicators)                       # (N, 3) before every update
    ekf.update(residual, H, R, policy=tuned)

    sh = SageHusa(b=0.97, R_min=1.0, R_max=1e4, adapt_Q=True)
    ekf.predict(F, Q, policy=sh)                          # Q̂ where estimated
    ekf.update(residual, H, R, policy=sh)
"""

from neuralmap.filters.policies.compose import Compose, quality_members
from neuralmap.filters.policies.gate import ChiSquareGate, chi_square_threshold
from neuralmap.filters.policies.huber import Huber, huber_weights
from neuralmap.filters.policies.igg3 import IGG3, igg3_weights
from neuralmap.filters.policies.inflation import InnovationInflation, innovation_inflation_factor
from neuralmap.filters.policies.quality import (
    QualityIndicator,
    QualityR,
    quality_factor,
    quality_membership,
)
from neuralmap.filters.policies.registry import (
    POLICIES,
    POLICY_NAMES,
    PolicyInfo,
    make_policy,
    policy_label,
)
from neuralmap.filters.policies.robust_adaptive import RobustAdaptive
from neuralmap.filters.policies.sage_husa import SageHusa, sage_husa_weight
from neuralmap.filters.policies.variational import VariationalAdaptive
from neuralmap.filters.policies.windowed_inflation import (
    WindowedInflation,
    windowed_inflation_factor,
)
from neuralmap.filters.policies.yang import YangAdaptive, yang_factor

__all__ = [
    "IGG3",
    "POLICIES",
    "POLICY_NAMES",
    "PolicyInfo",
    "ChiSquareGate",
    "Compose",
    "Huber",
    "InnovationInflation",
    "QualityIndicator",
    "QualityR",
    "RobustAdaptive",
    "SageHusa",
    "VariationalAdaptive",
    "WindowedInflation",
    "YangAdaptive",
    "chi_square_threshold",
    "huber_weights",
    "igg3_weights",
    "innovation_inflation_factor",
    "make_policy",
    "policy_label",
    "quality_factor",
    "quality_members",
    "quality_membership",
    "sage_husa_weight",
    "windowed_inflation_factor",
    "yang_factor",
]
