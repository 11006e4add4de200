"""LIBERO frames -> camera slots, against hand-computed pixels (truncation, antialiased resize, padding)."""

from __future__ import annotations

import pytest
import torch

from steering_core.pi05.preprocess import libero_camera_slots, resize_with_pad, to_model_range, to_uint8


def test_to_uint8_truncates_like_libero_inputs():
    frames = torch.tensor([0.5, 0.999, 1.0, 0.0, 0.0039, 1.2, -0.1]).reshape(1, 1, 1, 7).expand(1, 3, 1, 7)
    # 127.5 -> 127 (rounding would give 128), 254.745 -> 254, 0.99 -> 0; out-of-range values clamp
    assert to_uint8(frames)[0, 0, 0].tolist() == [127, 254, 255, 0, 0, 255, 0]


def test_downscale_is_antialiased_bilinear_rounded():
    # each row 0, 40, 80, 120; halving with a triangle filter of support 2 (weights 0.25, 0.75, 0.75, 0.25,
    # renormalised at the border): (0*.75 + 40*.75 + 80*.25) / 1.75 = 28.57 -> 29, (10 + 60 + 90) / 1.75 -> 91
    row = torch.tensor([0, 40, 80, 120], dtype=torch.uint8)
    images = row.expand(1, 3, 4, 4).clone()
    out = resize_with_pad(images, 2)
    assert out.dtype == torch.uint8
    assert out[0, 0].tolist() == [[29, 91], [29, 91]]


def test_pad_keeps_aspect_ratio_floor_half_on_top_left():
    wide = torch.full((1, 3, 1, 4), 200, dtype=torch.uint8)  # ratio 1: no resize, 3 rows of padding
    out = resize_with_pad(wide, 4)
    assert out[0, 0].tolist() == [[0] * 4, [200] * 4, [0] * 4, [0] * 4]
    tall = torch.full((1, 3, 8, 4), 100, dtype=torch.uint8)  # ratio 2 -> (4, 2), one column each side
    assert resize_with_pad(tall, 4)[0, 1].tolist() == [[0, 100, 100, 0]] * 4


def test_to_model_range():
    values = torch.tensor([0, 127, 255], dtype=torch.uint8)
    assert to_model_range(values).tolist() == pytest.approx([-1.0, 127 / 255 * 2 - 1, 1.0])


def test_libero_slots_hand_computed_and_not_rotated():
    image = torch.zeros(2, 3, 4, 4)
    image[:, :, 0, 0] = 1.0  # bright top-left pixel must stay top-left: nothing flips LeRobot frames
    wrist = (torch.tensor([0, 40, 80, 120]) / 255.0).expand(2, 3, 4, 4)
    images, masks = libero_camera_slots(image, wrist, image_size=4)
    assert [tuple(x.shape) for x in images] == [(2, 3, 4, 4)] * 3
    assert all(x.dtype == torch.float32 for x in images)
    assert images[0][0, 0, 0, 0] == 1.0 and images[0][0, 0, 3, 3] == -1.0 and images[0][0, 0, 0, 1] == -1.0
    # k/255 * 255 is exactly k in float32 for these k, so truncation keeps 0, 40, 80, 120
    wrist_row = [k / 255 * 2 - 1 for k in (0, 40, 80, 120)]
    assert images[1][1, 2, 3].tolist() == pytest.approx(wrist_row)
    assert (images[2] == -1.0).all()
    assert [m.tolist() for m in masks] == [[True, True], [True, True], [False, False]]
    small, _ = libero_camera_slots(image, wrist, image_size=2)
    # the hand values of test_downscale_is_antialiased_bilinear_rounded
    assert small[1][0, 0, 1].tolist() == pytest.approx([29 / 255 * 2 - 1, 91 / 255 * 2 - 1])


def test_real_size_frames_are_a_pure_resize():
    white = torch.ones(1, 3, 256, 256)
    images, _ = libero_camera_slots(white, white)
    assert images[0].shape == (1, 3, 224, 224) and (images[0] == 1.0).all()


def test_bad_frames_are_one_clear_error():
    with pytest.raises(ValueError) as err:
        libero_camera_slots(torch.zeros(2, 4, 8, 8), torch.zeros(2, 3, 8, 8, dtype=torch.uint8))
    message = str(err.value)
    assert "`image` is (2, 4, 8, 8) torch.float32, expected (B, 3, H, W) float in [0, 1]" in message
    assert "`wrist_image` is (2, 3, 8, 8) torch.uint8" in message
    with pytest.raises(ValueError, match="batch sizes differ: image 2, wrist_image 1"):
        libero_camera_slots(torch.zeros(2, 3, 8, 8), torch.zeros(1, 3, 8, 8))
