"""Court geometry: ITTF dimensions, side/edge queries, collision boxes."""

from __future__ import annotations

import numpy as np
import pytest

from studio import constants as C
from studio.physics.court import DEFAULT_COURT, Court


def test_law_dimensions() -> None:
    c = DEFAULT_COURT
    assert c.length == pytest.approx(2.74)
    assert c.width == pytest.approx(1.525)
    assert c.floor_z == pytest.approx(-0.76)
    assert c.server_end_line_x == pytest.approx(-1.37)
    assert c.net_half_span == pytest.approx(1.525 / 2 + 0.1525)


def test_boxes_match_geometry() -> None:
    boxes = {b.name: b for b in DEFAULT_COURT.boxes()}
    top = boxes["table_top"]
    # playing surface is the top face of the table box, at z = 0
    assert top.center[2] + top.half_size[2] == pytest.approx(0.0)
    assert top.half_size[0] == pytest.approx(1.37) and top.half_size[1] == pytest.approx(0.7625)
    net = boxes["net"]
    assert net.center[2] + net.half_size[2] == pytest.approx(C.NET_HEIGHT)
    for name in ("net_post_left", "net_post_right"):
        post = boxes[name]
        outer = abs(post.center[1]) + post.half_size[1]
        assert outer == pytest.approx(0.7625 + 0.1525)
        assert post.center[2] + post.half_size[2] == pytest.approx(C.NET_HEIGHT)
    # net and posts meet without a gap
    assert net.half_size[1] == pytest.approx(abs(boxes["net_post_left"].center[1]) - boxes["net_post_left"].half_size[1])


def test_on_table_and_edges() -> None:
    c = DEFAULT_COURT
    pts = np.array([[0.0, 0.0], [1.37, 0.7625], [1.3701, 0.0], [-1.0, -0.8]])
    assert c.on_table(pts).tolist() == [True, True, False, False]
    assert c.edge_distance([0.0, 0.0]) == pytest.approx(0.7625)
    assert c.edge_distance([1.3, 0.0]) == pytest.approx(0.07)
    assert c.edge_distance([1.5, 0.0]) == pytest.approx(-0.13)
    assert c.side(-0.01) == "server" and c.side(0.2) == "receiver"


def test_lines_lie_inside_surface() -> None:
    for line in DEFAULT_COURT.lines():
        assert abs(line.center[0]) + line.half_size[0] <= DEFAULT_COURT.half_length + 1e-12
        assert abs(line.center[1]) + line.half_size[1] <= DEFAULT_COURT.half_width + 1e-12


@pytest.mark.parametrize("field", ["length", "width", "net_height"])
@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan")])
def test_bad_dimensions_rejected(field: str, bad: float) -> None:
    with pytest.raises(ValueError, match=field):
        Court(**{field: bad})
