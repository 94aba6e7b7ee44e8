"""The ``--cluster`` option of the Monte Carlo studies (tan, tan_scale, learned, gnss_ins,
acquisition): where their independent tasks run (`neuralmap.cluster`)."""

from __future__ import annotations

from dataclasses import dataclass

from neuralmap.cluster import ClusterSpec, parse_cluster, require_distributed
from neuralmap.studies.base import StudyConfig

__all__ = ["ClusterOptions"]


@dataclass
class ClusterOptions(StudyConfig):
    """A study config that can deal its Monte Carlo tasks to a Dask cluster (a study's
    config lists it among its bases).

    Attributes:
        cluster: Where the tasks run: ``none`` (null, this process), ``local`` (a Dask
            LocalCluster of one single-threaded worker process per core), ``local:N``
            (N workers) or a running Dask scheduler's address (``tcp://HOST:8786``).
            The results are bit-identical to this process; a Dask run needs the ``dask``
            extra (``pip install 'neuralmap[dask]'``).
    """

    cluster: str | None = None

    def validate(self) -> None:
        """Checks the shared options, the cluster value and that Dask is installed when it
        is asked for (before any work; the scheduler's reachability is checked at the
        start of the Monte Carlo)."""
        super().validate()
        if parse_cluster(self.cluster).kind != "process":
            require_distributed(f"--cluster {self.cluster}")

    @property
    def cluster_spec(self) -> ClusterSpec:
        """The parsed `cluster`."""
        return parse_cluster(self.cluster)
