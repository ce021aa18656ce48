"""hfrep_blocks (one compiled pass) and field_report (the signed distance read from the unsigned
one, not copied) against the NumPy expressions they replaced, on a small sphere: equal bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.eikonal import signed_distance_blocks
from pipeline.hfrep import hfrep_blocks, step_function
from pipeline.quality import deviation_on_blocks, extra_zero_crossings, field_report, gradient_stats
from tests.test_eikonal import solved, sphere


@pytest.fixture(scope="module")
def sph():
    frep, _, res = solved(sphere, 32, max_vox=3.0)
    return frep, res


@pytest.mark.parametrize("step", ["sigmoid", "tanh", "rational"])
def test_hfrep_blocks_equal_the_numpy_expression(sph, step: str) -> None:
    frep, res = sph
    dist = res.distance
    values = np.where(res.inside, np.float32(1.0), np.float32(-1.0))
    rows = frep.block_index(dist.origins)
    hb = np.flatnonzero(rows >= 0)
    sub, fa = values[hb], frep.active[rows[hb]]
    sub[fa] = step_function(frep.values[rows[hb]][fa], step, 0.05)
    values[hb] = sub
    values *= dist.values
    values[~dist.active] = -dist.background
    got = hfrep_blocks(frep, res, step, 0.05)
    assert np.array_equal(got.values, values) and np.array_equal(got.active, dist.active)
    assert np.abs(sub[fa]).min() < 0.5  # the step matters: voxels next to the surface are far from +-1


def test_field_report_equals_the_report_of_the_signed_copy(sph) -> None:
    frep, res = sph
    hf = hfrep_blocks(frep, res)
    sd = signed_distance_blocks(res)
    band = 3 * frep.voxel_size
    want = {"frep": {"gradient": gradient_stats(frep), "deviation": deviation_on_blocks(frep, sd, band, -1.0)},
            "surface": {"gradient": gradient_stats(sd)},
            "hfrep": {"gradient": gradient_stats(hf),
                      "deviation": deviation_on_blocks(hf, sd, band, -1.0, near=frep.origins),
                      **extra_zero_crossings(hf, frep)}}
    assert field_report(frep, res, hf) == want
    assert want["surface"]["gradient"]["voxels"] > 5000 and want["frep"]["deviation"]["voxels"] > 1000
