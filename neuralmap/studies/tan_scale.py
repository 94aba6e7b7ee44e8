"""TAN Monte Carlo at scale (``study: tan_scale``): chunked runs in bounded memory.

The same scenario, map and methods as the TAN study (`neuralmap.studies.setup.prepare_tan`),
flown as `neuralmap.lab.chunked.run_monte_carlo_chunked` runs: seed blocks of 1024
runs, chunks of ``chunk_runs`` runs dealt to a Dask cluster (``--cluster``; default
``local``: a LocalCluster of one single-threaded worker per core, `neuralmap.cluster`).
Only per-run final errors and bounds and per-step sums are kept, so a million runs fit in
memory; the results do not depend on ``chunk_runs`` or ``cluster`` (bit-identical in
float64). Up to 1024 runs
the draws are those of the TAN study; the figures here are the reduced ones (RMSE curve,
final error, divergence by the filter's own bound), not the PCRB comparison.

Examples:
    python evaluate.py --config configs/tan_scale.yaml
    python evaluate.py --config configs/tan_scale.yaml --n_runs 100000 --cluster local:8
    python evaluate.py --config configs/tan_scale.yaml --cluster tcp://HOST:8786
    python evaluate.py --config configs/tan_scale.yaml --n_runs 20000 --cluster none
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from neuralmap.cluster import open_cluster
from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.chunked import BATCH_RUNS, SEED_BLOCK_RUNS, peak_rss_mb, run_monte_carlo_chunked
from neuralmap.outputs import StudyOutputs
from neuralmap.studies.cluster_options import ClusterOptions
from neuralmap.studies.setup import TanOptions, prepare_tan

__all__ = ["TanScaleConfig", "run"]


@dataclass
class TanScaleConfig(TanOptions, ClusterOptions):
    """Options of the chunked TAN study (the shared TAN options plus the chunking).

    Attributes:
        chunk_runs: Runs per chunk (whole filter batches), the unit dealt to a worker.
        batch_runs: Runs filtered as one batch (whole seed blocks of 1024); bounds memory.
            Larger batches pay the filter's per-step overhead less often; changing it may
            change results in the last bits, ``chunk_runs`` and ``cluster`` never do.
        cluster: Where the chunks run (`ClusterOptions`);
            default ``local``: a Dask LocalCluster of one single-threaded worker process per
            core this process may use (one chunk per core at a time; the filter is run
            single-threaded, where it is fastest per core). ``none`` = this process.
    """

    study: str = "tan_scale"
    experiment: str = "tan_scale"
    threads: int | None = 1
    progress: bool = True
    n_runs: int = 1_000_000
    methods: list[str] = field(default_factory=lambda: ["bilinear", "nine_point"])
    chunk_runs: int = BATCH_RUNS
    batch_runs: int = BATCH_RUNS
    cluster: str | None = "local"

    def validate(self) -> None:
        """Checks values (also those of the TAN study and the cluster value)."""
        super().validate()
        if self.chunk_runs < 1 or self.batch_runs < 1:
            raise NeuralMapError(
                f"--chunk_runs and --batch_runs must be >= 1, got "
                f"{self.chunk_runs}, {self.batch_runs}."
            )


def run(config: TanScaleConfig, outputs: StudyOutputs) -> None:
    """Runs the chunked Monte Carlo and writes the reduced metrics and the throughput."""

    setup = prepare_tan(scenario=config.scenario, methods=config.methods, map_path=config.map,
                        runs_dir=config.runs_dir, seed=config.seed,
                        neural_fit_variance=config.neural_fit_variance,
                        map_error_points=config.map_error_points, device=config.torch_device)
    setup.pin(config)
    with open_cluster(config.cluster) as dispatcher:
        workers = dispatcher.workers
        started = time.perf_counter()
        result = run_monte_carlo_chunked(
            setup.scenario, setup.methods, n_runs=config.n_runs, chunk_runs=config.chunk_runs,
            batch_runs=config.batch_runs, progress=config.progress,
            seed=setup.seed, cluster=dispatcher.client, threads=config.threads,
            dtype=config.torch_dtype, device=config.torch_device, tile=setup.tile,
            truth_terrain=setup.truth_terrain)
        wall = time.perf_counter() - started
    metrics = {name: s.metrics(divergence_sigma=config.divergence_sigma)
               for name, s in result.summaries.items()}
    rows = [[name, m["n_included"], m["rmse_pos_m"], m["final_pos_m"], m["divergence_rate"]]
            for name, m in metrics.items()]
    outputs.add_table("Reduced navigation metrics",
                      ["method", "runs kept", "RMSE pos (m, last half)", "final RMSE (m)",
                       "divergence rate (9 sigma)"], rows)
    runs_per_s = config.n_runs * len(metrics) / wall
    for name, m in metrics.items():  # TensorBoard summary scalars
        for key in ("rmse_pos_m", "final_pos_m", "divergence_rate"):
            outputs.log_scalar(f"summary/{key}/{name}", m[key])
    outputs.log_scalar("throughput/run_methods_per_s", runs_per_s)
    outputs.add_table(
        "Throughput", ["runs", "methods", "chunks", "cluster", "worker threads", "wall (s)",
                       "run-methods/s", "peak RSS (MiB, this process)"],
        [[config.n_runs, len(metrics), result.n_chunks, dispatcher.description, workers, wall,
          runs_per_s, peak_rss_mb()]],
        note=f"Seed blocks of {SEED_BLOCK_RUNS} runs, filter batches of {config.batch_runs}; "
             "results do not depend on the chunking or the cluster. Wall time once the cluster "
             "is up (its start not counted).")
    outputs.results.update({
        "methods": metrics, "t": result.t.tolist(), "n_chunks": result.n_chunks,
        "timing_s": {**result.timing_s, "wall": wall}, "runs_per_s": runs_per_s,
        "peak_rss_mb": peak_rss_mb(), "seed_block_runs": SEED_BLOCK_RUNS,
        "batch_runs": config.batch_runs,
        "cluster": {"spec": config.cluster, "description": dispatcher.description,
                    "worker_threads": workers},
    })
