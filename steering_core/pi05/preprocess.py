"""LIBERO frames -> pi0.5's three camera slots, exactly as openpi's inference transforms (spec 3.1).

physical-intelligence/libero style datasets are already in training orientation: nothing here rotates.
Raw LIBERO hdf5 renders must be flipped along H and W before they reach this module.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

# openpi's camera slots in prefix order; LIBERO fills the first two, the right wrist is absent (mask False)
CAMERA_SLOTS = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")
LIBERO_IMAGE_KEYS = ("image", "wrist_image")  # dataset features feeding the base and left-wrist slots
IMAGE_SIZE = 224


def to_uint8(frames: torch.Tensor) -> torch.Tensor:
    """Return uint8 (B, 3, H, W) from float (B, 3, H, W) in [0, 1]: x255 truncated, as LiberoInputs does.

    Values outside [0, 1] are clamped first (inside the range this is openpi's `(255 * x).astype(uint8)`).
    """
    scaled = frames.to(torch.float32) * 255.0
    return scaled.clamp(0.0, 255.0).to(torch.uint8)  # float -> uint8 casts truncate toward zero


def resize_with_pad(images: torch.Tensor, size: int = IMAGE_SIZE) -> torch.Tensor:
    """Return uint8 (B, 3, size, size): aspect-preserving antialiased bilinear resize, then zero padding.

    ratio = max(W, H) / size, new (int(H / ratio), int(W / ratio)), rounded and clipped to uint8; padding
    puts floor(diff / 2) rows/columns top/left and the rest bottom/right (openpi's resize_with_pad).
    """
    _, _, height, width = images.shape
    ratio = max(width / size, height / size)
    new_height, new_width = int(height / ratio), int(width / ratio)
    if (new_height, new_width) != (height, width):
        resized = F.interpolate(
            images.to(torch.float32), size=(new_height, new_width), mode="bilinear", align_corners=False, antialias=True
        )
        images = resized.round().clamp(0, 255).to(torch.uint8)  # round half to even, like jnp.round
    pad_top, pad_left = (size - new_height) // 2, (size - new_width) // 2
    # F.pad takes (left, right, top, bottom) for the last two dims
    padding = (pad_left, size - new_width - pad_left, pad_top, size - new_height - pad_top)
    return F.pad(images, padding, value=0)


def to_model_range(images: torch.Tensor) -> torch.Tensor:
    """Return float32 in [-1, 1] from uint8: x / 255 * 2 - 1."""
    return images.to(torch.float32) / 255.0 * 2.0 - 1.0


def libero_camera_slots(
    image: torch.Tensor,
    wrist_image: torch.Tensor,
    image_size: int = IMAGE_SIZE,
) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Return ([base, left wrist, right wrist] float32 (B, 3, size, size) in [-1, 1], [masks (B,) bool]).

    `image` (agentview) and `wrist_image` are float32 (B, 3, H, W) in [0, 1] as LeRobotDataset returns
    them. The right wrist is an all-zero image (all -1 after scaling) with mask False, as pi0.5 expects.
    """
    return camera_slots(*libero_uint8_cameras(image, wrist_image), image_size)


def libero_uint8_cameras(image: torch.Tensor, wrist_image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Return both cameras as uint8 (B, 3, H, W) (`to_uint8`) after checking them as `libero_camera_slots` does.

    The first half of `libero_camera_slots`: capture runs it in its frame workers and `camera_slots` on the
    model's device, a quarter of the float32 bytes copied there.
    """
    check_cameras(image, wrist_image)
    return to_uint8(image), to_uint8(wrist_image)


def check_cameras(image: torch.Tensor, wrist_image: torch.Tensor) -> None:
    """Raise one ValueError naming every camera that is not float (B, 3, H, W), or batch sizes that differ."""
    problems = []
    for name, frames in zip(LIBERO_IMAGE_KEYS, (image, wrist_image)):
        if frames.ndim != 4 or frames.shape[1] != 3 or not frames.dtype.is_floating_point:
            problems.append(f"`{name}` is {tuple(frames.shape)} {frames.dtype}, expected (B, 3, H, W) float in [0, 1]")
    if not problems and image.shape[0] != wrist_image.shape[0]:
        problems.append(f"batch sizes differ: image {image.shape[0]}, wrist_image {wrist_image.shape[0]}")
    if problems:
        raise ValueError("libero_camera_slots: " + "; ".join(problems))


def camera_slots(
    image: torch.Tensor, wrist_image: torch.Tensor, image_size: int = IMAGE_SIZE
) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Return the three camera slots and masks (as `libero_camera_slots`) from uint8 (B, 3, H, W) frames."""
    batch = image.shape[0]
    base = to_model_range(resize_with_pad(image, image_size))
    wrist = to_model_range(resize_with_pad(wrist_image, image_size))
    absent = torch.full_like(base, -1.0)  # to_model_range of an all-zero uint8 image
    present = torch.ones(batch, dtype=torch.bool)
    return [base, wrist, absent], [present, present.clone(), torch.zeros(batch, dtype=torch.bool)]


# lerobot camera names (after `observation.images.`) -> the LIBERO camera feeding that slot (spec 17.3)
LEROBOT_CAMERA_NAMES = {
    "image": "image", "agentview_image": "image", "base_0_rgb": "image",
    "wrist_image": "wrist_image", "image2": "wrist_image", "robot0_eye_in_hand_image": "wrist_image",
    "left_wrist_0_rgb": "wrist_image",
}


@dataclass(frozen=True)
class Cameras:
    """Which LIBERO camera fills each of a checkpoint's camera slots (None: absent, mask False), and whose
    preprocessing turns frames into slots: openpi's (uint8 truncation, antialiased resize of uint8) by default, or
    lerobot's (the float frames resized bilinearly without antialiasing, clamped, zero-padded)."""

    slots: tuple[str | None, ...] = ("image", "wrist_image", None)
    lerobot: bool = False

    @classmethod
    def of_lerobot(cls, keys: tuple[str, ...], where: str) -> Cameras:
        """Return the cameras of a lerobot policy's VISUAL features in order (`observation.images.<name>`)."""
        slots = []
        for key in keys:
            name = key.removeprefix("observation.images.")
            if name.startswith("empty_camera_"):
                slots.append(None)
            elif name in LEROBOT_CAMERA_NAMES:
                slots.append(LEROBOT_CAMERA_NAMES[name])
            else:
                raise ValueError(f"{where}: camera `{key}` is not one of LIBERO's two; expected observation.images."
                                 f"<{'|'.join(LEROBOT_CAMERA_NAMES)}> or an empty camera")
        # lerobot fills the cameras present in the batch first and appends the missing ones
        return cls(tuple(sorted(slots, key=lambda slot: slot is None)), lerobot=True)

    def worker_uint8(self, image: torch.Tensor, wrist_image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Return float (B, 3, H, W) frames in [0, 1] as uint8 for the trip to the device: truncated as openpi's
        LiberoInputs does, or rounded (lossless for frames decoded from uint8) for lerobot's float path."""
        if not self.lerobot:
            return libero_uint8_cameras(image, wrist_image)
        check_cameras(image, wrist_image)  # the same checks; the values are rounded, not truncated
        return tuple((frames.to(torch.float32) * 255.0).round().clamp(0, 255).to(torch.uint8)
                     for frames in (image, wrist_image))

    def from_uint8(self, image: torch.Tensor, wrist_image: torch.Tensor, size: int
                   ) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Return the slots (B, 3, size, size) float32 in [-1, 1] and masks (B,) bool of uint8 (B, 3, H, W) frames."""
        if not self.lerobot:
            return camera_slots(image, wrist_image, size)
        return self.from_float(image.to(torch.float32) / 255.0, wrist_image.to(torch.float32) / 255.0, size)

    def from_float(self, image: torch.Tensor, wrist_image: torch.Tensor, size: int
                   ) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Return the slots and masks of float (B, 3, H, W) frames in [0, 1], as LeRobotDataset returns them."""
        if not self.lerobot:
            return libero_camera_slots(image, wrist_image, size)
        check_cameras(image, wrist_image)
        frames = {"image": _lerobot_resize(image.to(torch.float32), size),
                  "wrist_image": _lerobot_resize(wrist_image.to(torch.float32), size)}
        batch = image.shape[0]
        slots, masks = [], []
        for slot in self.slots:
            present = slot is not None
            slots.append(frames[slot] * 2.0 - 1.0 if present else torch.full_like(frames["image"], -1.0))
            masks.append(torch.full((batch,), present, dtype=torch.bool, device=image.device))
        return slots, masks


def _lerobot_resize(frames: torch.Tensor, size: int) -> torch.Tensor:
    """Return float frames (B, 3, size, size) in [0, 1]: lerobot's resize_with_pad_torch of float images (bilinear,
    no antialiasing, clamped to [0, 1], centred zero padding with the odd row/column at the bottom/right)."""
    _, _, height, width = frames.shape
    if (height, width) == (size, size):
        return frames
    ratio = max(width / size, height / size)
    new_height, new_width = int(height / ratio), int(width / ratio)
    resized = F.interpolate(frames, size=(new_height, new_width), mode="bilinear", align_corners=False)
    resized = resized.clamp(0.0, 1.0)
    pad_top, pad_left = (size - new_height) // 2, (size - new_width) // 2
    padding = (pad_left, size - new_width - pad_left, pad_top, size - new_height - pad_top)
    return F.pad(resized, padding, value=0.0)
