"""Sequential composition of update policies (quality R then α; robust weights then α).

``Compose(p1, p2, ...)`` runs the policies in order on one update: each sees the context
as adapted by the ones before it (their ``R``, predicted covariance and rejections), so
``Compose(QualityR(...), InnovationInflation(c0))`` tunes R before the α test (paper 003)
and ``Compose(IGG3(k0, k1), YangAdaptive(c0, c1))`` computes Yang's Δ with the equivalent
``R̄`` (the robust adaptive filter of SEEDS 002). The merged adaptation:

* ``R``: the last one given; ``keep``: the intersection;
* predicted covariance: a replacement ``P_prior`` of a later policy supersedes the earlier
  ones (it is expressed in terms of the context it saw), factors ``p_scale`` multiply;
* ``info``: every entry, prefixed with its policy's name (``"igg3.weight"``).

At most one member may iterate (``iterations > 1``; e.g. the variational filter), and it
must be the last; its refinements are merged with the fixed adaptations of the others.
``predict`` hooks chain (each sees the Q adapted by the previous one).
"""

from __future__ import annotations

from dataclasses import replace

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.policies._common import and_keep
from neuralmap.filters.policy import Adaptation, FilterPolicy, Posterior, UpdateContext
from neuralmap.filters.stats import symmetrize

__all__ = ["Compose", "quality_members"]




class Compose(FilterPolicy):
    """Policies applied in sequence on one update (see the module docstring).

    Args:
        *policies: The policies, in application order (at least one).
        name: Report name (default ``"compose"``).

    Raises:
        NeuralMapError: No policies, a non-policy, or an iterating member not last.
    """

    name = "compose"

    def __init__(self, *policies: FilterPolicy, name: str | None = None) -> None:
        if not policies:
            raise NeuralMapError("Compose: give at least one policy.")
        for p in policies:
            if not isinstance(p, FilterPolicy):
                raise NeuralMapError(
                    f"Compose: {p!r} is not a FilterPolicy (robust/adaptive update policy)."
                )
        iterating = [i for i, p in enumerate(policies) if int(p.iterations) > 1]
        if len(iterating) > 1 or (iterating and iterating[0] != len(policies) - 1):
            raise NeuralMapError(
                "Compose: at most one iterating policy (e.g. VariationalAdaptive) is "
                "supported and it must come last."
            )
        self.policies = list(policies)
        self.iterations = max(int(p.iterations) for p in policies)
        if name is not None:
            self.name = name
        names = [p.name for p in self.policies]
        self._prefixes = [
            f"{n}{i}" if names.count(n) > 1 else n for i, n in enumerate(names)
        ]
        self._contexts: list[UpdateContext] = []
        self._adaptations: list[Adaptation] = []
        self._fixed: Adaptation | None = None

    def reset(self) -> None:
        """Resets every member."""
        for p in self.policies:
            p.reset()

    def set_quality(self, values: object) -> None:
        """Forwards quality indicators to the members that take them (`QualityR`),
        at any depth (a composition inside a composition, e.g. `RobustAdaptive`)."""
        takers = quality_members(self)
        if not takers:
            raise NeuralMapError(
                "Compose.set_quality: no member takes quality indicators (add a QualityR, "
                "e.g. QualityR.altimeter(), to the composition)."
            )
        for p in takers:
            p.set_quality(values)  # type: ignore[attr-defined]

    @staticmethod
    def _advance(context: UpdateContext, a: Adaptation) -> UpdateContext:
        """The context the next policy sees after adaptation ``a``."""
        P, hpht = context.P_prior, context.HPHt
        if a.P_prior is not None:
            P = a.P_prior
            if a.p_scale is not None:
                P = P * a.p_scale.reshape(-1, 1, 1)
            hpht = symmetrize(torch.matmul(torch.matmul(context.H, P), context.H.transpose(1, 2)))
        elif a.p_scale is not None:
            s = a.p_scale.reshape(-1, 1, 1)
            P, hpht = P * s, hpht * s
        return replace(
            context,
            P_prior=P,
            HPHt=hpht,
            R=context.R if a.R is None else a.R,
            keep=and_keep(context.keep, a.keep),
        )

    def _merge(self, merged: Adaptation, a: Adaptation, prefix: str) -> Adaptation:
        if a.P_prior is not None:
            P_prior, p_scale = a.P_prior, a.p_scale
        elif a.p_scale is not None:
            P_prior = merged.P_prior
            p_scale = a.p_scale if merged.p_scale is None else merged.p_scale * a.p_scale
        else:
            P_prior, p_scale = merged.P_prior, merged.p_scale
        info = dict(merged.info)
        info.update({f"{prefix}.{k}": v for k, v in a.info.items()})
        return Adaptation(
            p_scale=p_scale,
            P_prior=P_prior,
            R=merged.R if a.R is None else a.R,
            keep=and_keep(merged.keep, a.keep),
            info=info,
        )

    def adapt(self, context: UpdateContext) -> Adaptation:
        """Each member's adaptation on the context left by the previous ones, merged."""
        merged = Adaptation()
        self._contexts, self._adaptations = [], []
        ctx = context
        for i, (p, prefix) in enumerate(zip(self.policies, self._prefixes, strict=True)):
            a = p.adapt(ctx)
            self._contexts.append(ctx)
            self._adaptations.append(a)
            if i == len(self.policies) - 1:
                self._fixed = merged
            merged = self._merge(merged, a, prefix)
            if i < len(self.policies) - 1:
                ctx = self._advance(ctx, a)
        return merged

    def refine(
        self, context: UpdateContext, adaptation: Adaptation, posterior: Posterior
    ) -> Adaptation | None:
        """Delegates to the last member; merges its refinement with the fixed part."""
        last = self.policies[-1]
        nxt = last.refine(self._contexts[-1], self._adaptations[-1], posterior)
        if nxt is None:
            return None
        self._adaptations[-1] = nxt
        assert self._fixed is not None
        return self._merge(self._fixed, nxt, self._prefixes[-1])

    def commit(
        self,
        context: UpdateContext,
        adaptation: Adaptation,
        posterior: Posterior,
        applied: torch.Tensor,
    ) -> None:
        """Every member commits on its own context and adaptation."""
        for p, ctx, a in zip(self.policies, self._contexts, self._adaptations, strict=True):
            p.commit(ctx, a, posterior, applied)

    def process_noise(
        self, *, F: torch.Tensor, Q: torch.Tensor, P: torch.Tensor
    ) -> torch.Tensor | None:
        """Chains the members' process-noise hooks (None when none adapts Q)."""
        out: torch.Tensor | None = None
        for p in self.policies:
            q = p.process_noise(F=F, Q=Q if out is None else out, P=P)
            if q is not None:
                out = q
        return out


def quality_members(policy: FilterPolicy | None) -> list[FilterPolicy]:
    """Every policy inside ``policy`` (itself, or the members of a composition at any depth)
    that reads quality indicators through ``set_quality``.

    Args:
        policy: A policy, a composition, or None.

    Returns:
        The leaf policies with a ``set_quality`` method, in application order.
    """
    if policy is None:
        return []
    if isinstance(policy, Compose):
        return [found for inner in policy.policies for found in quality_members(inner)]
    return [policy] if callable(getattr(policy, "set_quality", None)) else []
