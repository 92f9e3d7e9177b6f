"""The PointNet++ network is the paper's: levels, radii, widths, and the same function as a naive
PointNet++ forward pass (32 sampled centres with repeats, fixed-size ball groups, MLP on concatenation)."""

import numpy as np
import pytest
import torch

from assets.biotac import electrode_table
from learn.nets import (
    FC_WIDTH,
    LEVEL_CENTRES,
    LEVEL_GROUP_SIZES,
    LEVEL_MLPS,
    LEVEL_RADII,
    POSITION_SCALE,
    PlainMLP,
    PointNet2,
    ball_groups,
    farthest_point_order,
    plan_levels,
)

torch.set_num_threads(1)
TARGETS = {"contact_loc": 3, "force": 3, "nodal": 128 * 3}


def test_architecture_numbers_are_the_papers() -> None:
    assert LEVEL_CENTRES == (32, 8, 1)
    assert LEVEL_RADII[:2] == (2.5e-3, 7e-3) and np.isinf(LEVEL_RADII[2])
    assert LEVEL_MLPS == ((64, 64, 128), (128, 128, 256), (256, 256, 512)) and FC_WIDTH == 1024
    net = PointNet2(electrode_table().positions, TARGETS)
    widths = [m.out_features for m in net.fc if isinstance(m, torch.nn.Linear)]
    assert widths == [1024, 1024]
    out = net(torch.rand(5, 19))
    assert {k: tuple(v.shape) for k, v in out.items()} == {"contact_loc": (5, 3), "force": (5, 3), "nodal": (5, 384)}


def test_sampling_and_grouping() -> None:
    points = electrode_table().positions
    order = farthest_point_order(points, 32)
    assert sorted(set(order[:19].tolist())) == list(range(19)), "every electrode once before any repeat"
    np.testing.assert_array_equal(order[19:], order[:13])
    groups = ball_groups(points, points[order[:8]], 7e-3, 16)
    dist = np.linalg.norm(points[groups] - points[order[:8]][:, None], axis=2)
    assert (dist <= 7e-3).all()
    plans = plan_levels(points)
    assert [len(p.centres) for p in plans[:2]] == [19, 8]  # 32 centres of which 19 distinct
    assert plans[0].groups.shape[1] == 1, "no two electrodes lie within 2.5 mm of each other"


def _naive_level(features, points, centres, groups, radius, level) -> torch.Tensor:
    """PointNet++ set abstraction as written: MLP on [member features, (member - centre) / radius]."""
    grouped = features[:, torch.as_tensor(groups)]
    offsets = torch.as_tensor((points[groups] - centres[:, None]) / radius, dtype=torch.float32)
    x = torch.cat([grouped, offsets.expand(len(features), -1, -1, -1)], dim=-1)
    weight = torch.cat([level.point_layer.weight, level.offset_layer.weight], dim=1)
    x = torch.relu(level.first_norm(x @ weight.T + level.point_layer.bias))
    return level.rest(x).amax(dim=2)


def test_network_equals_a_naive_pointnet2_forward_pass() -> None:
    torch.manual_seed(0)
    points = electrode_table().positions
    net = PointNet2(points, TARGETS)
    net.train()
    net(torch.rand(64, 19))  # move the batch-norm statistics away from their defaults
    net.eval()
    values = torch.rand(7, 19)
    features = torch.cat([values[..., None], net.point_features.expand(7, -1, -1)], dim=-1)
    for level_id in range(2):
        centres = points[farthest_point_order(points, LEVEL_CENTRES[level_id])]
        groups = ball_groups(points, centres, LEVEL_RADII[level_id], LEVEL_GROUP_SIZES[level_id])
        features = _naive_level(features, points, centres, groups, LEVEL_RADII[level_id], net.levels[level_id])
        points = centres
    everything = np.arange(len(points))[None]
    features = _naive_level(features, points, np.zeros((1, 3)), everything, POSITION_SCALE, net.levels[2])
    expected = net.heads(net.fc(features[:, 0]))
    got = net(values)
    for k in TARGETS:
        torch.testing.assert_close(got[k], expected[k], rtol=1e-5, atol=1e-6)


def test_plain_mlp_shapes() -> None:
    out = PlainMLP(19, TARGETS)(torch.rand(3, 19))
    assert out["nodal"].shape == (3, 384)


@pytest.mark.parametrize("count", [1, 8, 19, 40])
def test_farthest_point_order_length(count: int) -> None:
    assert len(farthest_point_order(electrode_table().positions, count)) == count
