import numpy as np
import pytest

from toptag.geometry import nearest_rotation, rodrigues, rotation_vector, vehicle_to_world, wrap_angle

pytestmark = pytest.mark.unit


@pytest.mark.parametrize("angle", [0.0, 1e-10, 1e-4, 0.7, np.pi / 2, 2.5, np.pi - 1e-4, np.pi - 1e-11])
def test_rotation_vector_round_trips_over_the_whole_range(angle):
    rng = np.random.default_rng(int(angle * 1e6) % 1000)
    for _ in range(20):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        R = rodrigues(axis * angle)
        assert np.abs(rodrigues(rotation_vector(R)) - R).max() < 1e-12


def test_wrap_angle_range():
    a = wrap_angle(np.array([-np.pi, np.pi, 3 * np.pi, -3 * np.pi + 1e-9, 0.5]))
    assert np.all(a > -np.pi) and np.all(a <= np.pi) and np.isclose(a[0], np.pi) and np.isclose(a[4], 0.5)


def test_nearest_rotation_is_a_rotation():
    M = np.random.default_rng(5).normal(size=(3, 3))
    R = nearest_rotation(M)
    assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)


def test_vehicle_to_world_at_many_poses_is_one_pose_at_a_time_to_the_bit():
    """sim.sampling.in_some_view_many places a vehicle at thousands of poses in one call and is checked
    against one pose at a time (test_site): the same numbers, not just close ones."""
    rng = np.random.default_rng(11)
    points = rng.uniform(-6, 6, (8, 3))
    poses = np.c_[rng.uniform(-60, 60, 500), rng.uniform(-60, 60, 500), rng.uniform(-4, 4, 500), rng.uniform(2, 4, 500)]
    many = vehicle_to_world(points, *poses.T)
    assert many.shape == (500, 8, 3)
    one = np.stack([vehicle_to_world(points, *p) for p in poses])
    np.testing.assert_array_equal(many, one)
    c, s = np.cos(poses[0, 2]), np.sin(poses[0, 2])
    x, y, z = points[0]
    assert np.allclose(one[0, 0], [c * x - s * y + poses[0, 0], s * x + c * y + poses[0, 1], z + poses[0, 3]], atol=1e-12)
