"""The ``--cluster`` values, the in-process dispatcher and the missing-Dask message."""

from __future__ import annotations

import sys

import pytest

from neuralmap.cluster import ClusterSpec, Dispatcher, default_workers, open_cluster, parse_cluster
from neuralmap.exceptions import NeuralMapError


@pytest.mark.parametrize(("value", "expected"), [
    (None, ClusterSpec("process")),
    ("none", ClusterSpec("process")),
    (" None ", ClusterSpec("process")),
    ("local:3", ClusterSpec("local", workers=3)),
    ("tcp://10.0.0.5:8786", ClusterSpec("scheduler", workers=0, address="tcp://10.0.0.5:8786")),
    ("tls://head:8786", ClusterSpec("scheduler", workers=0, address="tls://head:8786")),
])
def test_parse_cluster(value, expected) -> None:  # noqa: ANN001
    assert parse_cluster(value) == expected


def test_local_is_one_worker_per_usable_core() -> None:
    import os

    spec = parse_cluster("local")
    assert spec.kind == "local" and spec.workers == default_workers()
    assert spec.workers == len(os.sched_getaffinity(0))


@pytest.mark.parametrize("value", ["local:0", "local:x", "local:-2", "locl", "10.0.0.5:8786",
                                   "tcp://", 4])
def test_parse_cluster_refuses(value) -> None:  # noqa: ANN001
    with pytest.raises(NeuralMapError, match="--cluster"):
        parse_cluster(value)


def _square_plus(shared: int, job: int) -> int:
    return job * job + shared


def test_in_process_dispatcher_keeps_job_order_and_reports_each() -> None:
    seen = []
    with open_cluster("none") as dispatcher:
        assert dispatcher.client is None and dispatcher.workers == 1
        out = dispatcher.map(_square_plus, [3, 1, 2], shared=10,
                             on_done=lambda i, r: seen.append((i, r)))
    assert out == [19, 11, 14]
    assert seen == [(0, 19), (1, 11), (2, 14)]


def test_missing_dask_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "distributed", None)  # import raises ImportError
    with pytest.raises(NeuralMapError, match=r"neuralmap\[dask\]"), open_cluster("local:2"):
        pass
    with pytest.raises(NeuralMapError, match=r"neuralmap\[dask\]"):
        Dispatcher(client=object()).map(_square_plus, [1], shared=0)


def test_an_object_that_is_no_client_is_refused() -> None:
    with pytest.raises(NeuralMapError, match="distributed.Client"), open_cluster(3.5):
        pass


def test_a_study_asking_for_dask_without_it_is_refused_at_validation(
        monkeypatch: pytest.MonkeyPatch) -> None:
    from neuralmap.studies.tan_scale import TanScaleConfig

    TanScaleConfig(cluster="none").validate()
    monkeypatch.setitem(sys.modules, "distributed", None)
    TanScaleConfig(cluster="none").validate()  # this process needs no Dask
    with pytest.raises(NeuralMapError, match=r"--cluster local.*neuralmap\[dask\]"):
        TanScaleConfig().validate()  # the default local cluster
