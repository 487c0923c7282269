"""Shared test helpers: brute-force enumeration and the location of ../shared/data."""

from __future__ import annotations

import itertools
import os
from pathlib import Path

import pytest
import torch

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

if os.environ.get("PYTEST_XDIST_WORKER"):
    # pytest -n 2 on 2 cores: one intra-op thread per worker, or the workers' thread pools
    # oversubscribe the cores and small batched ops slow down tenfold
    torch.set_num_threads(1)


def requires_shared_data():
    """Skip (with the reason) when ../shared/data is not beside the checkout."""
    return pytest.mark.skipif(
        not SHARED_DATA.is_dir(), reason=f"needs the shared data folder at {SHARED_DATA}"
    )


def enumerate_scores(unary: torch.Tensor, groups) -> tuple[torch.Tensor, torch.Tensor]:
    """Score of every joint configuration by brute force.

    Args:
        unary: (B, V, K) log-potentials.
        groups: list of (edges (E, 2), dense log tables broadcastable to (B, E, K, K)).

    Returns:
        configs (K**V, V) long and scores (B, K**V).
    """
    b, v, k = unary.shape
    configs = torch.tensor(list(itertools.product(range(k), repeat=v)), dtype=torch.long)
    scores = unary[:, torch.arange(v)[None, :], configs].sum(-1)  # (B, C)
    for edges, table in groups:
        table = table.expand(b, edges.shape[0], k, k)
        for e, (a, bb) in enumerate(edges.tolist()):
            scores = scores + table[:, e, configs[:, a], configs[:, bb]]
    return configs, scores


def brute_marginals(configs: torch.Tensor, scores: torch.Tensor, k: int) -> torch.Tensor:
    """(B, V, K) exact marginal probabilities from enumerated scores."""
    p = torch.softmax(scores, -1)  # (B, C)
    onehot = torch.nn.functional.one_hot(configs, k).to(p.dtype)  # (C, V, K)
    return torch.einsum("bc,cvk->bvk", p, onehot)


def cli_error_line(capsys, main, argv: list[str]) -> str:
    """Run a CLI's ``main`` in-process; it must exit 2 with exactly one ``error: ...`` line on
    stderr. Returns the message after ``error: ``."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.endswith("\n") and err.count("\n") == 1, err
    return err[len("error: ") : -1]


def assert_message(message: str, expected: str) -> None:
    """``expected`` is the exact message, or a regular expression after ``re:``."""
    import re

    if expected.startswith("re:"):
        assert re.fullmatch(expected[3:], message), message
    else:
        assert message == expected
