"""Capture's frame loading: uint8 cameras from the workers, pi0.5's camera slots computed on the model's device."""

from __future__ import annotations

from types import SimpleNamespace

import pyarrow as pa
import pytest
import torch
from torch.utils.data import default_collate

from steering_core.capture import frames as frames_module
from steering_core.capture.frames import frame_loader, frame_workers, slots_on_device
from steering_core.data.dataset import DatasetMeta, EpisodeInfo
from steering_core.pi05 import libero_camera_slots

DEVICES = [
    "cpu",
    pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here")),
]
# CUDA's antialiased bilinear kernel sums the same weights in another order than the CPU one, so a value within
# float32 rounding of a .5 boundary may round to the neighbouring level: at most one uint8 level (2/255 after
# scaling to [-1, 1]), on at most 1% of the values (such ties are rare; any real kernel difference moves far more).
ONE_LEVEL = 2 / 255 + 1e-6
CUDA_DIFFERING_FRACTION = 0.01


def lerobot_items(count: int, height: int, width: int) -> list[dict]:
    """Return `count` frames as LeRobotDataset returns them: decoded uint8 / 255, float32 (3, H, W) in [0, 1]."""
    generator = torch.Generator().manual_seed(height * width + count)
    items = []
    for index in range(count):
        image, wrist = (torch.randint(0, 256, (3, height, width), generator=generator) for _ in range(2))
        items.append({"image": image.float() / 255, "wrist_image": wrist.float() / 255, "task": "open the drawer",
                      "index": index})
    return items


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("height, width", [(256, 256), (200, 256), (256, 97)])
def test_slots_on_the_device_equal_the_old_worker_path(device, height, width):
    items = lerobot_items(3, height, width)
    plan = [("0", [0, 1]), ("0", [2])]
    # the old path: the workers collated and ran libero_camera_slots on the float frames
    old = []
    for _, positions in plan:
        batch = default_collate([items[p] for p in positions])
        old.append(libero_camera_slots(batch["image"], batch["wrist_image"], 224))

    loader = frame_loader(items, plan, ("image", "wrist_image", "task", "index"), num_workers=0, pin_memory=False)
    for (images, masks), batch in zip(old, loader, strict=True):
        assert batch["image"].dtype == batch["wrist_image"].dtype == torch.uint8  # what the workers hand over
        new = slots_on_device(batch, 224, torch.device(device))
        assert "image" not in new and "wrist_image" not in new and new["task"] == batch["task"]
        assert all(slot.device.type == device and slot.dtype == torch.float32 for slot in new["images"])
        assert [m.tolist() for m in new["image_masks"]] == [m.tolist() for m in masks]
        for ours, reference in zip(new["images"], images):
            ours = ours.cpu()
            if device == "cpu":
                assert torch.equal(ours, reference)
            else:
                difference = (ours - reference).abs()
                assert difference.max() <= ONE_LEVEL
                assert (difference > 0).float().mean() <= CUDA_DIFFERING_FRACTION


def test_the_right_wrist_slot_is_absent():
    loader = frame_loader(lerobot_items(2, 16, 16), [("0", [0, 1])], ("image", "wrist_image"), 0, False)
    new = slots_on_device(next(iter(loader)), 8, torch.device("cpu"))
    assert (new["images"][2] == -1).all() and new["image_masks"][2].tolist() == [False, False]


def test_bad_frames_fail_in_the_worker_naming_the_camera():
    items = [{"image": torch.zeros(4, 8, 8), "wrist_image": torch.zeros(3, 8, 8)}]
    loader = frame_loader(items, [("0", [0])], ("image", "wrist_image"), 0, False)
    with pytest.raises(ValueError, match=r"`image` is \(1, 4, 8, 8\) torch.float32, expected \(B, 3, H, W\) float"):
        next(iter(loader))


class UndecodableFrames(list):
    """Frames whose second one fails to decode, as Pillow fails on a corrupt PNG deep in a dataset."""

    def __getitem__(self, position):
        if position == 1:
            raise OSError("cannot identify image file <_io.BytesIO object>")
        return super().__getitem__(position)


def test_a_frame_that_cannot_be_decoded_is_one_value_error():
    items = UndecodableFrames(lerobot_items(2, 16, 16))
    loader = frame_loader(items, [("0", [0, 1])], ("image", "wrist_image"), 0, False)
    with pytest.raises(ValueError, match=r"^the frame at dataset position 1 cannot be decoded \(cannot identify"):
        next(iter(loader))


class StoredFrames(list):
    """Decoded frames of episode 3 over the stored columns lerobot's dataset holds (`hf_dataset.data`)."""

    def __init__(self, items: list[dict]):
        super().__init__(items)
        self.hf_dataset = SimpleNamespace(data=pa.table({"episode_index": [3] * len(items),
                                                         "frame_index": list(range(len(items)))}))


def test_a_video_frame_of_another_shape_than_declared_is_refused(tmp_path):
    items = StoredFrames(lerobot_items(2, 16, 16))
    items[1]["wrist_image"] = torch.zeros(1, 16, 16)  # a grayscale frame among RGB ones
    features = {key: {"dtype": "video", "shape": [16, 16, 3]} for key in ("image", "wrist_image")}
    meta = DatasetMeta(tmp_path, {"features": features}, {0: "open"}, (EpisodeInfo(3, ("open",), 2, 0, 2, "d.parquet"),))
    loader = frame_loader(items, [("0", [0, 1])], ("image", "wrist_image"), 0, False, meta)
    with pytest.raises(ValueError, match=r"d.parquet: episode 3 frame 1 has camera\(s\) \{'wrist_image': \(1, 16, 16\)\}"):
        next(iter(loader))


def test_a_worker_error_comes_back_as_its_own_line():
    def batches():
        yield {"index": 0}
        raise ValueError("Caught ValueError in DataLoader worker process 0.\nOriginal Traceback (most recent call "
                         "last):\n  File \"x.py\", line 1\nValueError: episode 3 frame 1 has camera(s) ...")
    with pytest.raises(ValueError) as raised:
        list(frames_module._worker_errors(batches()))
    assert str(raised.value) == "episode 3 frame 1 has camera(s) ..."


@pytest.mark.parametrize("cores, workers", [(1, 0), (2, 1), (3, 2), (9, 8), (16, 8), (128, 8)])
def test_default_workers_leave_one_core_to_the_main_process(monkeypatch, cores, workers):
    monkeypatch.setattr(frames_module, "usable_cores", lambda: cores)
    assert frame_workers(None) == workers
    assert frame_workers(0) == 0 and frame_workers(cores) == cores  # an explicit count is kept, within the cores
