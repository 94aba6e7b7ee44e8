"""Chunked Monte Carlo: the same results, bit for bit, whatever the chunking or the cluster;
filters on one truth dealt to a Dask cluster: the same as in this process."""

from __future__ import annotations

import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.chunked import block_seed, run_monte_carlo_chunked
from neuralmap.lab.monte_carlo import run_monte_carlo
from neuralmap.lab.scenario import load_scenario, scenario_tile
from neuralmap.linearize.factory import make_linearizer


@pytest.fixture(scope="module")
def dask_client():  # noqa: ANN201
    """A 2-worker Dask LocalCluster as ``--cluster local:2`` starts it (worker processes,
    one thread each), without the dashboard."""
    pytest.importorskip("distributed")
    from neuralmap.cluster import open_cluster

    with open_cluster("local:2", dashboard_address=None) as dispatcher:
        assert dispatcher.workers == 2
        yield dispatcher.client


@pytest.fixture(scope="module")
def setup():  # noqa: ANN201
    scenario = load_scenario("tiny")
    tile = scenario_tile(scenario)
    methods = {"bilinear": make_linearizer("bilinear", tile=tile),
               "nine_point": make_linearizer("nine_point", tile=tile)}
    return scenario, tile, methods


def _same(a, b) -> None:  # noqa: ANN001
    for name in a.summaries:
        sa, sb = a.summaries[name], b.summaries[name]
        for key in ("final_pos_err", "final_sigma", "included", "healthy", "est_left",
                    "sum_pos2", "sum_vel2"):
            assert torch.equal(getattr(sa, key), getattr(sb, key)), key
        assert torch.equal(a.err[name], b.err[name])
        assert sa.metrics() == {**sb.metrics(), "elapsed_s": sa.elapsed_s}


def test_chunked_equals_one_chunk(setup) -> None:  # noqa: ANN001
    scenario, tile, methods = setup
    kwargs = {"n_runs": 5, "seed": 5, "tile": tile, "keep_errors": True, "block_runs": 2,
              "batch_runs": 2}
    one = run_monte_carlo_chunked(scenario, methods, chunk_runs=8, **kwargs)
    many = run_monte_carlo_chunked(scenario, methods, chunk_runs=2, **kwargs)
    odd = run_monte_carlo_chunked(scenario, methods, chunk_runs=3, **kwargs)  # 2 blocks/chunk
    assert (one.n_chunks, many.n_chunks, odd.n_chunks) == (1, 3, 2)
    _same(one, many)
    _same(one, odd)
    assert one.err["bilinear"].shape == (5, scenario.n_steps + 1, 5)


def test_batches_of_several_blocks_do_not_depend_on_the_chunking(setup) -> None:  # noqa: ANN001
    scenario, tile, methods = setup
    kwargs = {"n_runs": 7, "seed": 5, "tile": tile, "keep_errors": True, "block_runs": 2,
              "batch_runs": 4}
    one = run_monte_carlo_chunked(scenario, methods, chunk_runs=8, **kwargs)
    many = run_monte_carlo_chunked(scenario, methods, chunk_runs=1, **kwargs)  # 1 batch/chunk
    assert (one.n_chunks, many.n_chunks) == (1, 2)
    _same(one, many)


def test_dask_cluster_equals_one_process(setup, dask_client) -> None:  # noqa: ANN001
    """Chunks dealt to two Dask worker processes: bit-identical to this process, run by run."""
    scenario, tile, methods = setup
    kwargs = {"n_runs": 7, "seed": 5, "tile": tile, "keep_errors": True, "block_runs": 2,
              "batch_runs": 2, "chunk_runs": 2}
    from distributed import get_task_stream

    here = run_monte_carlo_chunked(scenario, methods, **kwargs)
    with get_task_stream(dask_client) as stream:
        dask = run_monte_carlo_chunked(scenario, methods, cluster=dask_client, **kwargs)
    chunks = [task for task in stream.data if str(task["key"]).startswith("tan-chunk")]
    assert len(chunks) == here.n_chunks == dask.n_chunks == 4  # every chunk ran on a worker
    _same(here, dask)


def test_filters_on_a_dask_cluster_equal_this_process(setup, dask_client) -> None:  # noqa: ANN001
    """One filter per task (the TAN and learned studies' Monte Carlo): every FilterRun field
    bit-identical to run_filter here, a policy and a second tuning included."""
    import dataclasses

    from distributed import get_task_stream

    from neuralmap.filters.policies.registry import make_policy
    from neuralmap.lab.monte_carlo import FilterJob, run_filters
    from neuralmap.lab.simulator import simulate

    scenario, tile, methods = setup
    truth = simulate(scenario, tile, n_runs=6, seed=3)
    tuned = dataclasses.replace(scenario, R_m2=4.0 * scenario.R_m2)
    jobs = {"bilinear": FilterJob(methods["bilinear"], scenario),
            "nine_point": FilterJob(methods["nine_point"], tuned),
            "igg3": FilterJob(methods["bilinear"], scenario, policy=make_policy("igg3"))}
    here = run_filters(truth, jobs)
    with get_task_stream(dask_client) as stream:
        dask = run_filters(truth, jobs, cluster=dask_client)
    assert len([t for t in stream.data if str(t["key"]).startswith("tan-filter")]) == 3
    assert list(dask) == list(jobs)
    for name in jobs:
        for f in dataclasses.fields(here[name]):
            a, b = getattr(here[name], f.name), getattr(dask[name], f.name)
            if isinstance(a, torch.Tensor):  # exact, NaN where no update happened
                torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True,
                                           msg=f"{name}.{f.name}")
    assert not torch.equal(here["bilinear"].P, here["nine_point"].P)  # the jobs differ


def test_first_block_is_the_plain_simulation(setup) -> None:  # noqa: ANN001
    scenario, tile, methods = setup
    plain = run_monte_carlo(scenario, methods, n_runs=6, seed=5, progress=False, tile=tile)
    chunked = run_monte_carlo_chunked(scenario, methods, n_runs=6, seed=5, tile=tile,
                                      keep_errors=True)
    for name in methods:
        assert torch.equal(plain.runs[name].err, chunked.err[name])
    # the reduction agrees with the plain run's figures (independent NumPy-style reference)
    err = plain.runs["bilinear"].err
    included = plain.truth.on_map.all(dim=1)
    pos2 = (err[..., 0] ** 2 + err[..., 1] ** 2)[included]
    expected_curve = pos2.mean(0).sqrt()
    got = chunked.summaries["bilinear"].metrics()
    assert torch.allclose(torch.tensor(got["rmse_pos_curve"], dtype=torch.float64),
                          expected_curve, rtol=1e-12)


def test_block_seeds_distinct_and_stable() -> None:
    seeds = [block_seed(7, b) for b in range(100)]
    assert seeds[0] == 7 and len(set(seeds)) == 100
    assert all(0 <= s < 2**63 for s in seeds)
    assert block_seed(7, 3) == block_seed(7, 3) != block_seed(8, 3)


def test_bad_counts(setup) -> None:  # noqa: ANN001
    scenario, tile, methods = setup
    with pytest.raises(NeuralMapError, match="chunk_runs"):
        run_monte_carlo_chunked(scenario, methods, n_runs=4, chunk_runs=0, tile=tile)
    with pytest.raises(NeuralMapError, match="methods"):
        run_monte_carlo_chunked(scenario, {}, n_runs=4, tile=tile)


def test_all_finite_equals_the_boolean_reference() -> None:
    from neuralmap.lab.chunked import _all_finite

    x = torch.randn(7, 4, 5, 5, dtype=torch.float64) * 1e300
    x[1, 2, 0, 3] = float("nan")
    x[3, 0, 4, 4] = float("inf")
    x[4, 3, 1, 1] = -float("inf")
    x[5, 1, 2, 2] = float("nan")
    x[5, 2, 2, 2] = float("inf")
    x[6] = torch.finfo(torch.float64).max  # finite however large
    expected = torch.isfinite(x).flatten(1).all(1)
    assert expected.tolist() == [True, False, True, False, False, False, True]
    assert torch.equal(_all_finite(x), expected)
