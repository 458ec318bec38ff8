"""A map's coverage on its ground plane, on references laid out on a known grid."""

from __future__ import annotations

import numpy as np
import pytest

from services.self_evaluation.coverage import HeldOut, coverage, ground_plane


def test_the_ground_plane_is_the_one_the_centres_spread_over() -> None:
    rng = np.random.default_rng(2)
    # a floor at eye height: x and z spread over metres, y within a few centimetres
    centers = np.column_stack(
        [rng.uniform(0, 8, 200), 1.6 + rng.normal(0, 0.02, 200), rng.uniform(0, 4, 200)]
    )
    origin, u, v = ground_plane(centers)
    np.testing.assert_allclose(origin, centers.mean(axis=0))
    assert abs(np.cross(u, v)[1]) > 0.999  # the normal is the vertical
    assert abs(u[0]) > 0.99  # the longer spread first


def test_cells_are_weak_where_held_out_references_failed_or_stand_alone() -> None:
    # a row of cells 1 m wide along x: two references in cells 0 to 3, one in cell 4
    xs = [0.2, 0.7, 1.2, 1.7, 2.2, 2.7, 3.2, 3.7, 4.5]
    centers = np.array([[x, 0.0, 0.01 * (i % 2)] for i, x in enumerate(xs)])
    held_out = [
        HeldOut(0, True, 0.01, 0.2),
        HeldOut(2, False, np.inf, np.inf),  # cell 1: one of one failed
        HeldOut(4, True, 0.02, 0.3),
        HeldOut(5, True, 0.40, 0.3),  # cell 2: one of two off by 40 cm
    ]
    cells = coverage(centers, held_out, cell_m=1.0).cells
    assert [c.references for c in cells] == [2, 2, 2, 2, 1]
    assert [c.held_out for c in cells] == [1, 1, 2, 0, 0]
    assert [c.why_weak for c in cells] == [
        [],
        ["1 of 1 references held out failed"],
        ["1 of 2 references held out failed"],
        [],
        ["a single reference"],
    ]
    assert cells[2].median_error_m == pytest.approx(0.21)
    assert cells[1].median_error_m is None


def test_cells_are_weak_where_half_their_queries_failed() -> None:
    # cells 1 m wide along x, two references each
    centers = np.array(
        [[x, 0.0, 0.01 * (i % 2)] for i, x in enumerate([0.2, 0.7, 1.2, 1.7, 2.2, 2.7])]
    )
    queries = {
        0: (3, 2),  # cell 0: 2 of 5 failed
        2: (1, 2),
        3: (0, 2),  # cell 1: 4 of 5 failed, over two references
        4: (0, 4),  # cell 2: 4 of 4 failed, too few to tell
    }
    cells = coverage(centers, [], cell_m=1.0, queries=queries).cells
    assert [(c.queries_localized, c.queries_failed) for c in cells] == [(3, 2), (1, 4), (0, 4)]
    assert [c.why_weak for c in cells] == [[], ["4 of 5 queries failed"], []]
