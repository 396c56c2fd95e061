"""Run a block with one torch thread: reductions then sum in one fixed order, so that two forwards
compare bit for bit whatever the machine's core count."""

from __future__ import annotations

import contextlib

import torch


@contextlib.contextmanager
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
