"""Test-suite settings shared by every test module."""

from __future__ import annotations

import torch

# One torch thread: on the 2-core CI machine OpenMP oversubscription (torch threads next to
# numpy/BLAS and other processes) made small tensor operations 10-100x slower.
torch.set_num_threads(1)
