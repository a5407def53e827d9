"""Limits on sizes: each refusal follows from its stated estimate."""

from __future__ import annotations

import pytest

from fricjax.errors import FricjaxError
from fricjax.limits import (
    HALF_LENGTH_PER_Q,
    MAX_RK4_STEPS,
    chain_bytes,
    check_chains,
    check_decimation,
    check_substeps,
)


def test_chains_are_refused_exactly_where_the_estimate_exceeds_memory() -> None:
    # the paper twin: 232 samples after trimming, 26 free parameters, 300 levels
    per_chain = chain_bytes(232, 26, 300)
    assert per_chain == 8 * (232 * 34 + 900)
    memory = 1000 * per_chain
    check_chains(1000, 232, 26, 300, "t", memory=memory)
    with pytest.raises(FricjaxError, match=r"1001 chains need about .*at most 1000 fit"):
        check_chains(1001, 232, 26, 300, "t", memory=memory)


def test_substeps_cap_counts_every_interval() -> None:
    n = 272
    most = MAX_RK4_STEPS // (n - 1)
    check_substeps(most, n, "simulate")
    with pytest.raises(FricjaxError, match=rf"use at most {most}$"):
        check_substeps(most + 1, n, "simulate")


@pytest.mark.parametrize("q", [2, 3, 10, 37])
def test_the_decimation_limit_is_below_the_filters_real_half_length(q: int) -> None:
    from fricjax.data.decimate import antialias_kernel

    half = (antialias_kernel(q).shape[0] - 1) // 2
    # the premise of the limit: the filter is never shorter than HALF_LENGTH_PER_Q·q, so
    # a record the limit refuses could not have been decimated anyway (needs n > half)
    assert half >= HALF_LENGTH_PER_Q * q
    with pytest.raises(FricjaxError, match="anti-alias filter"):
        check_decimation(q, HALF_LENGTH_PER_Q * q, "validate")
    check_decimation(q, half + 1, "validate")
    check_decimation(1, 2, "validate")  # no decimation: no filter, no limit
