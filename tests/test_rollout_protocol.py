"""openpi's LIBERO preprocessing: axis-angle of the eef quaternion, resize with padding, the observation element."""

import math

import numpy as np
import pytest
from helpers_rollout import reference_resize_with_pad

from steering_core.rollout.protocol import (
    MAX_STEPS,
    max_steps,
    policy_observation,
    preprocess_image,
    quat2axisangle,
    resize_with_pad,
)


def test_quat2axisangle_identity_is_zero():
    assert np.array_equal(quat2axisangle(np.array([0.0, 0.0, 0.0, 1.0])), np.zeros(3))


def test_quat2axisangle_quarter_turn_about_z():
    half = math.pi / 4
    quat = np.array([0.0, 0.0, math.sin(half), math.cos(half)])
    np.testing.assert_allclose(quat2axisangle(quat), [0.0, 0.0, math.pi / 2], atol=1e-12)


def test_quat2axisangle_half_turn_about_x_as_libero_eef_rests():
    np.testing.assert_allclose(quat2axisangle(np.array([1.0, 0.0, 0.0, 0.0])), [math.pi, 0.0, 0.0], atol=1e-12)


def test_quat2axisangle_near_zero_rotation():
    angle = 1e-6
    quat = np.array([math.sin(angle / 2), 0.0, 0.0, math.cos(angle / 2)])
    np.testing.assert_allclose(quat2axisangle(quat), [angle, 0.0, 0.0], rtol=1e-3)
    # w rounding above 1 is clipped to 1: no rotation, no NaN, and the input is left alone
    over = np.array([1e-9, 0.0, 0.0, 1.0 + 1e-12])
    assert np.array_equal(quat2axisangle(over), np.zeros(3))
    assert over[3] == 1.0 + 1e-12


def test_resize_with_pad_pads_a_wide_image_top_and_bottom():
    image = np.arange(2 * 4 * 3, dtype=np.uint8).reshape(2, 4, 3)
    out = resize_with_pad(image, 4)  # ratio 1: no resampling, one zero row above and below
    expected = np.zeros((4, 4, 3), dtype=np.uint8)
    expected[1:3] = image
    assert np.array_equal(out, expected)


def test_resize_with_pad_of_a_uniform_tall_image():
    out = resize_with_pad(np.full((256, 128, 3), 77, dtype=np.uint8), 224)
    # ratio 256 / 224: 224 x 112, centred with 56 zero columns each side
    assert out.shape == (224, 224, 3) and out.dtype == np.uint8
    assert (out[:, 56:168] == 77).all() and (out[:, :56] == 0).all() and (out[:, 168:] == 0).all()


@pytest.mark.parametrize("shape", [(256, 256, 3), (128, 256, 3), (200, 99, 3)])
def test_resize_with_pad_matches_pil_reference(shape):
    image = np.random.default_rng(sum(shape)).integers(0, 256, shape, dtype=np.uint8)
    assert np.array_equal(resize_with_pad(image, 224), reference_resize_with_pad(image, 224))


def test_square_image_of_the_target_size_is_unchanged():
    image = np.random.default_rng(1).integers(0, 256, (224, 224, 3), dtype=np.uint8)
    assert resize_with_pad(image) is image


def test_policy_observation_rotates_resizes_and_lays_out_the_state():
    rng = np.random.default_rng(2)
    agentview, wrist = (rng.integers(0, 256, (256, 256, 3), dtype=np.uint8) for _ in range(2))
    obs = {
        "robot0_eef_pos": np.array([0.1, 0.2, 0.3]),
        "robot0_eef_quat": np.array([1.0, 0.0, 0.0, 0.0]),
        "robot0_gripper_qpos": np.array([0.04, -0.04]),
    }
    element = policy_observation((agentview, wrist), obs, "turn on the stove")
    assert sorted(element) == ["observation/image", "observation/state", "observation/wrist_image", "prompt"]
    assert np.array_equal(element["observation/image"], reference_resize_with_pad(np.rot90(agentview, 2), 224))
    assert np.array_equal(element["observation/wrist_image"], preprocess_image(wrist))
    state = element["observation/state"]
    assert state.dtype == np.float64 and state.shape == (8,)
    np.testing.assert_allclose(state, [0.1, 0.2, 0.3, math.pi, 0.0, 0.0, 0.04, -0.04], atol=1e-12)
    assert element["prompt"] == "turn on the stove"


def test_max_steps_are_openpis():
    assert MAX_STEPS == {
        "libero_spatial": 220,
        "libero_object": 280,
        "libero_goal": 300,
        "libero_10": 520,
        "libero_90": 400,
    }
    with pytest.raises(ValueError, match="no step budget for LIBERO suite 'libero_100'"):
        max_steps("libero_100")
