"""Dynamics tests run torch single-threaded.

The batches here are tiny, and on a shared 2-core machine MKL's thread pool turns a 4x4 matmul
into milliseconds whenever the other core is busy; one thread keeps these tests fast and steady.
"""

import pytest
import torch


@pytest.fixture(autouse=True)
def single_torch_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
