"""Monte Carlo at scale: runs in seed blocks, chunks that bound memory, dealt to Dask.

`neuralmap.lab.simulator.simulate` draws every random number of all N runs from one
generator, so runs ``0 … N−1`` depend on N. Here the runs are grouped into **seed blocks**
of `SEED_BLOCK_RUNS` runs; block ``b`` is simulated on its own with seed
`block_seed` (``seed`` itself for block 0, a splitmix64 hash of ``(seed, b)`` after)
and the world (truth terrain) built once from ``seed``. A chunk is a whole number of seed
blocks, so a run's truth, its filter outputs and every reduction are the same whatever
the chunk size or the number of processes (bit-identical in float64). Up to
`SEED_BLOCK_RUNS` runs, the draws are exactly those of ``simulate`` (the study's
default results are unchanged); beyond, they are a different (equally valid) sample.

Every seed block is simulated on its own and the blocks of one **filter batch**
(``batch_runs``, 8 blocks by default, fixed by the block index) are filtered together (a
batched kernel may round differently for another batch size, so the batches never depend
on the chunking); a chunk is whole filter batches, the unit dealt to a worker. Memory: one
batch's truth and filter histories (``O(batch · K · 25)`` floats) live only while the
batch runs; what is kept is per run a handful of numbers (final errors and
bounds, flags) and per step running sums, added per seed block in block order; glibc is
told to return large freed blocks to the system (`bound_allocator`), so resident
memory stays flat over a long run.

The chunks run in this process or on a Dask cluster (``cluster``: ``local:N``, a scheduler
address or a `distributed.Client`; `neuralmap.cluster`); the world, tile and
methods are scattered to the workers once, and the progress comes from the finished chunks.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, fields, replace
from typing import Any

import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.metrics import diverged_runs
from neuralmap.lab.scenario import Scenario, load_scenario, scenario_tile
from neuralmap.lab.simulator import Truth, simulate

__all__ = [
    "BATCH_RUNS",
    "SEED_BLOCK_RUNS",
    "ChunkedResult",
    "MethodSummary",
    "block_seed",
    "bound_allocator",
    "concat_truths",
    "run_monte_carlo_chunked",
    "simulate_blocks",
]

#: Runs per seed block (the unit of seeding; chunks are whole multiples of it).
SEED_BLOCK_RUNS = 1024
#: Runs filtered as one batch by default (8 seed blocks): the filter's per-step cost is
#: mostly fixed overhead at 1024 runs, so larger batches run several times faster.
BATCH_RUNS = 8 * SEED_BLOCK_RUNS
_MASK64 = (1 << 64) - 1


#: Allocations at or above this size go to their own memory maps (returned to the system
#: when freed); see `bound_allocator`. Above a filter step's temporaries (a batch's
#: ``(8192, 5, 5)`` covariance is 1.6 MiB), below a batch's histories (hundreds of MiB).
MMAP_THRESHOLD_BYTES = 32 << 20
#: Free memory at the top of the heap kept for reuse rather than returned (trimmed).
TRIM_THRESHOLD_BYTES = 64 << 20


def bound_allocator() -> bool:
    """Makes glibc return freed large blocks to the system (best effort; False if not glibc).

    glibc raises its mmap threshold dynamically after large blocks are freed, so the
    per-block tensors of later seed blocks are carved from the heap, which fragments: the
    resident memory of a long chunked run then creeps up (measured: +100 MiB after 20 k
    jacksboro runs). A fixed threshold (``mallopt(M_MMAP_THRESHOLD, 32 MiB)``, as the
    ``MALLOC_MMAP_THRESHOLD_`` environment variable) keeps it flat: a filter batch's
    histories (hundreds of MiB) get their own maps, returned when freed, while a filter
    step's temporaries reuse the heap (at 1 MiB every step's batch covariance was a fresh
    map, and its page faults were about a third of a 1 M-run Monte Carlo's CPU time);
    ``M_TRIM_THRESHOLD`` 64 MiB keeps the heap top from being returned and refaulted.
    """
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        # -3 = M_MMAP_THRESHOLD, -1 = M_TRIM_THRESHOLD
        return bool(libc.mallopt(-3, MMAP_THRESHOLD_BYTES)) and bool(
            libc.mallopt(-1, TRIM_THRESHOLD_BYTES))
    except (OSError, AttributeError):
        return False


def block_seed(seed: int, block: int) -> int:
    """Seed of seed block ``block``: ``seed`` for block 0, else splitmix64(seed, block).

    Returns:
        A non-negative integer below 2⁶³ (valid for ``torch.Generator.manual_seed``).
    """
    if block == 0:
        return int(seed)
    z = (int(seed) * 0x9E3779B97F4A7C15 + int(block) + 0x9E3779B97F4A7C15) & _MASK64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK64
    return (z ^ (z >> 31)) & 0x7FFF_FFFF_FFFF_FFFF


def _block_sizes(n_runs: int, block_runs: int) -> list[int]:
    """Sizes of the seed blocks of ``n_runs`` runs."""
    full, rest = divmod(n_runs, block_runs)
    return [block_runs] * full + ([rest] if rest else [])


def simulate_blocks(
    scenario: Scenario, tile: DemTile, *, blocks: list[int], sizes: list[int], seed: int,
    truth_terrain: Any, dtype: torch.dtype, device: str | torch.device,
) -> list[Truth]:
    """The truths of the given seed blocks (each simulated on its own seed).

    Without the altimeter quality record (the chunked filters use no quality-aware policy;
    the draws are the same).
    """
    return [simulate(scenario, tile, n_runs=sizes[b], seed=block_seed(seed, b), dtype=dtype,
                     device=device, truth_terrain=truth_terrain, quality=False)
            for b in blocks]


@dataclass
class MethodSummary:
    """What is kept of one method's runs (memory ``O(N)`` small values, ``O(K)`` sums).

    Attributes:
        final_pos_err: ``(N,)`` final horizontal error, m.
        final_sigma: ``(N,)`` filter's final 1σ horizontal bound ``sqrt(P_xx + P_yy)``, m.
        included: ``(N,)`` truth stayed on the map and errors are finite.
        healthy: ``(N,)`` filter stayed numerically healthy.
        est_left: ``(N,)`` the estimate left the map at some step.
        sum_pos2: ``(K+1,)`` sum over included runs of the squared horizontal error.
        sum_vel2: ``(K+1,)`` the same for the velocity error.
        elapsed_s: Filter time, s (summed over chunks).
    """

    final_pos_err: torch.Tensor
    final_sigma: torch.Tensor
    included: torch.Tensor
    healthy: torch.Tensor
    est_left: torch.Tensor
    sum_pos2: torch.Tensor
    sum_vel2: torch.Tensor
    elapsed_s: float = 0.0

    def metrics(self, *, divergence_sigma: float = 9.0,
                pcrb_final: float | None = None, pcrb_factor: float = 5.0) -> dict[str, Any]:
        """RMSE curve and figures as `neuralmap.lab.metrics.navigation_metrics`.

        Divergence: final error above ``divergence_sigma`` × the filter's 1σ, or above
        ``pcrb_factor`` × ``pcrb_final`` when given, or the estimate left the map.
        """
        n_inc = int(self.included.sum())
        diverged = diverged_runs(self.final_pos_err, self.final_sigma, included=self.included,
                                 healthy=self.healthy, est_left=self.est_left,
                                 pcrb_final=pcrb_final, pcrb_factor=pcrb_factor,
                                 divergence_sigma=divergence_sigma)
        half = self.sum_pos2.shape[0] // 2
        curve = (self.sum_pos2 / max(n_inc, 1)).sqrt()
        return {
            "n_runs": int(self.included.shape[0]),
            "n_included": n_inc,
            "n_diverged": int(diverged.sum()),
            "divergence_rate": int(diverged.sum()) / n_inc if n_inc else None,
            "rmse_pos_m": math.sqrt(float(self.sum_pos2[half:].sum()) / (
                max(n_inc, 1) * (self.sum_pos2.shape[0] - half))) if n_inc else None,
            "final_pos_m": float(curve[-1]) if n_inc else None,
            "rmse_pos_curve": curve.tolist() if n_inc else None,
            "elapsed_s": self.elapsed_s,
        }


@dataclass
class ChunkedResult:
    """What `run_monte_carlo_chunked` returns.

    Attributes:
        summaries: Method name to its `MethodSummary`.
        n_runs: Runs N.
        n_chunks: Chunks run.
        t: ``(K+1,)`` sample times.
        timing_s: Simulation and filter seconds.
        err: Method name to ``(N, K+1, 5)`` errors (only with ``keep_errors=True``).
    """

    summaries: dict[str, MethodSummary]
    n_runs: int
    n_chunks: int
    t: torch.Tensor
    timing_s: dict[str, float] = field(default_factory=dict)
    err: dict[str, torch.Tensor] | None = None


def _all_finite(x: torch.Tensor) -> torch.Tensor:
    """``(N,)``: every entry of run n finite; the same as ``isfinite(x).flatten(1).all(1)``
    from two reductions (NaN propagates through both, ±inf shows in one) instead of a
    boolean copy of the whole history (the covariance history of a filter batch is
    hundreds of MiB; the copy took a large share of a chunk's time)."""
    flat = x.flatten(1)
    return torch.isfinite(flat.amax(1)) & torch.isfinite(flat.amin(1))


def _block_reduce(run: Any, sizes: list[int]) -> list[dict[str, torch.Tensor]]:
    """Per seed block: per-run values and per-step sums of one method's chunk run."""
    err = run.err.detach().to("cpu", torch.float64)
    P = run.P.detach().to("cpu", torch.float64)
    finite = _all_finite(err) & _all_finite(P)
    included = ~run.off_map.cpu() & finite
    pos2 = err[..., 0] ** 2 + err[..., 1] ** 2
    vel2 = err[..., 3] ** 2 + err[..., 4] ** 2
    out, start = [], 0
    for size in sizes:
        sl = slice(start, start + size)
        inc = included[sl]
        out.append({
            "final_pos_err": pos2[sl, -1].sqrt().clone(),
            "final_sigma": (P[sl, -1, 0, 0] + P[sl, -1, 1, 1]).clamp(min=0.0).sqrt().clone(),
            "included": inc.clone(),
            "healthy": run.healthy.detach().cpu()[sl].clone(),
            "est_left": (~run.est_on_map.detach().cpu()[sl].all(dim=1)).clone(),
            "sum_pos2": torch.where(inc[:, None], pos2[sl], 0.0).clone().sum(0),
            "sum_vel2": torch.where(inc[:, None], vel2[sl], 0.0).clone().sum(0),
        })
        start += size
    return out


def concat_truths(truths: list[Truth]) -> Truth:
    """The seed blocks' truths as one batch (runs in block order; shared fields from the first).

    Args:
        truths: Truths of the same scenario and world, ``(N_b, K+1, …)`` each.

    Returns:
        One `Truth` with ``N = Σ N_b`` runs.
    """
    if len(truths) == 1:
        return truths[0]
    first = truths[0]
    batched = {}
    for f in fields(first):
        value = getattr(first, f.name)
        if f.name != "t" and isinstance(value, torch.Tensor):
            batched[f.name] = torch.cat([getattr(tr, f.name) for tr in truths])
    return replace(first, **batched)


def _run_chunk(shared: dict[str, Any], job: dict[str, Any]) -> dict[str, Any]:
    """Runs a chunk's filter batches one after the other; returns their per-block reductions.

    Each seed block draws from its own generator; the seed blocks of one filter batch
    (``job["batches"]``, fixed by the global block index) are concatenated and filtered as
    one batch, so the per-step overhead is paid once per batch, not once per block. A
    batched kernel may round differently for another batch size (seen at the ulp level
    for a batch of one), so the batches never depend on the chunking.

    Args:
        shared: The inputs every chunk reads (scenario, tile, world, methods, sizes...).
        job: ``{"batches": [[block, ...], ...]}``, this chunk's filter batches.
    """
    from neuralmap.lab.monte_carlo import run_filter

    job = {**shared, **job}
    torch.set_num_threads(int(job.get("threads", 1)))
    bound_allocator()
    reduced: dict[str, list[dict[str, torch.Tensor]]] = {name: [] for name in job["methods"]}
    errors: dict[str, list[torch.Tensor]] = {name: [] for name in job["methods"]}
    filt = dict.fromkeys(job["methods"], 0.0)
    sim_s, t = 0.0, None
    for blocks in job["batches"]:
        tick = time.perf_counter()
        truth = concat_truths(simulate_blocks(
            job["scenario"], job["tile"], blocks=blocks, sizes=job["sizes"],
            seed=job["seed"], truth_terrain=job["truth_terrain"], dtype=job["dtype"],
            device=job["device"]))
        sim_s += time.perf_counter() - tick
        t = truth.t.cpu()
        for name, linearizer in job["methods"].items():
            run = run_filter(truth, linearizer, job["scenario"], method=name)
            reduced[name].extend(_block_reduce(run, [job["sizes"][b] for b in blocks]))
            filt[name] += run.elapsed_s
            if job["keep_errors"]:
                errors[name].append(run.err.detach().cpu())
            del run
        del truth
    return {"blocks": [b for blocks in job["batches"] for b in blocks], "reduced": reduced,
            "errors": {k: torch.cat(v) for k, v in errors.items() if v}, "sim_s": sim_s,
            "filter_s": filt, "t": t}


def run_monte_carlo_chunked(
    scenario: Scenario | str,
    methods: dict[str, Any],
    *,
    n_runs: int,
    chunk_runs: int = 8 * SEED_BLOCK_RUNS,
    seed: int | None = None,
    cluster: Any = None,
    threads: int = 1,
    dtype: torch.dtype = torch.float64,
    device: str | torch.device = "cpu",
    tile: DemTile | None = None,
    truth_terrain: Any = None,
    keep_errors: bool = False,
    block_runs: int = SEED_BLOCK_RUNS,
    batch_runs: int = BATCH_RUNS,
    progress: bool = False,
) -> ChunkedResult:
    """Monte Carlo TAN in chunks of seed blocks, in this process or on a Dask cluster.

    Args:
        scenario: A `Scenario` or a shipped name / YAML path.
        methods: Method name to linearizer (picklable when ``cluster`` is given).
        n_runs: Runs N.
        chunk_runs: Runs per chunk (rounded up to whole filter batches), the unit dealt
            to a worker.
        seed: Simulation seed (None = ``scenario.seed``).
        cluster: Where the chunks run (`neuralmap.cluster.open_cluster`): None or
            ``"none"`` = this process; ``"local:N"`` = a Dask LocalCluster of N
            single-threaded workers started for this call; ``"tcp://HOST:8786"`` = a running
            Dask scheduler; or an open `distributed.Client`.
        threads: Torch threads per chunk (in this process or on each worker).
        dtype: Filter dtype.
        device: Torch device of the truth and filters.
        tile: The scenario's tile, when loaded.
        truth_terrain: The world, when built (else built once from ``seed``).
        keep_errors: Also return every run's ``(K+1, 5)`` errors (tests; memory ``O(N·K)``).
        block_runs: Runs per seed block (changing it changes the draws).
        batch_runs: Runs filtered as one batch (rounded up to whole seed blocks); bounds
            memory (one batch's truth and filter histories). Changing it may change the
            results in the last bits; ``chunk_runs`` and ``cluster`` never do.
        progress: A progress bar over the runs, advanced as chunks finish (plain lines with
            a heartbeat when stdout is not a terminal, `neuralmap.progress`).

    Returns:
        `ChunkedResult`; the same, bit for bit, for any ``chunk_runs``/``cluster``.

    Raises:
        NeuralMapError: Bad counts, empty methods, a bad ``cluster`` or Dask not installed.
    """
    from neuralmap.cluster import open_cluster
    from neuralmap.lab.truth_terrain import true_terrain

    scenario = load_scenario(scenario)
    if not isinstance(methods, dict) or not methods:
        raise NeuralMapError("run_monte_carlo_chunked: methods must be a non-empty dict.")
    for what, value in (("n_runs", n_runs), ("chunk_runs", chunk_runs),
                        ("block_runs", block_runs), ("batch_runs", batch_runs)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise NeuralMapError(
                f"run_monte_carlo_chunked: {what} must be an integer >= 1, got {value!r}.")
    seed = scenario.seed if seed is None else int(seed)
    if tile is None:
        tile = scenario_tile(scenario)
    if truth_terrain is None:
        truth_terrain = true_terrain(scenario, tile, seed=seed)
    sizes = _block_sizes(n_runs, block_runs)
    per_batch = max(1, math.ceil(batch_runs / block_runs))
    batches = [list(range(i, min(i + per_batch, len(sizes))))
               for i in range(0, len(sizes), per_batch)]
    per_chunk = max(1, math.ceil(chunk_runs / (per_batch * block_runs)))
    chunks = [batches[i:i + per_chunk] for i in range(0, len(batches), per_chunk)]
    base = {"scenario": scenario, "tile": tile, "truth_terrain": truth_terrain, "seed": seed,
            "sizes": sizes, "methods": methods, "dtype": dtype, "device": str(device),
            "keep_errors": keep_errors, "threads": threads}
    jobs = [{"batches": batch_list} for batch_list in chunks]
    bar = None

    def done(_: int, out: dict[str, Any]) -> None:
        if bar is not None:
            bar.update(sum(sizes[b] for b in out["blocks"]))

    with open_cluster(cluster) as dispatcher:
        if progress:
            from neuralmap.progress import progress_bar

            bar = progress_bar(total=n_runs, unit="run", desc=(
                f"chunked Monte Carlo ({len(jobs)} chunks, {dispatcher.description})"))
        try:
            outputs = dispatcher.map(_run_chunk, jobs, shared=base, on_done=done,
                                     on_idle=None if bar is None else lambda: bar.update(0),
                                     name="tan-chunk")
        finally:
            if bar is not None:
                bar.close()
    by_block: dict[int, dict[str, dict[str, torch.Tensor]]] = {}
    for out in outputs:
        for i, b in enumerate(out["blocks"]):
            by_block[b] = {name: red[i] for name, red in out["reduced"].items()}
    summaries = {}
    for name in methods:
        parts = [by_block[b][name] for b in range(len(sizes))]
        sum_pos2, sum_vel2 = parts[0]["sum_pos2"].clone(), parts[0]["sum_vel2"].clone()
        for part in parts[1:]:  # block order: the same additions for any chunking
            sum_pos2 += part["sum_pos2"]
            sum_vel2 += part["sum_vel2"]
        summaries[name] = MethodSummary(
            **{key: torch.cat([p[key] for p in parts]) for key in
               ("final_pos_err", "final_sigma", "included", "healthy", "est_left")},
            sum_pos2=sum_pos2, sum_vel2=sum_vel2,
            elapsed_s=float(sum(o["filter_s"][name] for o in outputs)))
    errors = None
    if keep_errors:
        errors = {name: torch.cat([o["errors"][name] for o in outputs]) for name in methods}
    return ChunkedResult(
        summaries=summaries, n_runs=n_runs, n_chunks=len(chunks), t=outputs[0]["t"],
        timing_s={"simulate": float(sum(o["sim_s"] for o in outputs)),
                  "filter": float(sum(sum(o["filter_s"].values()) for o in outputs))},
        err=errors)


def peak_rss_mb() -> float:
    """Peak resident set size of this process, MiB (Linux)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0

