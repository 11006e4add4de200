"""Episode videos: an MP4 decodes back to the frames written (count, size, close pixels); no frames are refused."""

from __future__ import annotations

import av
import numpy as np
import pytest

from steering_core.rollout.video import video_codec, write_video


def moving_frames(count: int = 12, side: int = 224) -> list[np.ndarray]:
    """Smooth frames (a gradient and a moving square): what a codec keeps well, unlike noise."""
    y, x = np.mgrid[0:side, 0:side]
    frames = []
    for t in range(count):
        frame = np.stack([x * 255 // side, y * 255 // side, np.full_like(x, 128)], axis=-1).astype(np.uint8)
        frame[40:90, 10 + 8 * t: 60 + 8 * t] = (250, 30, 30)
        frames.append(frame)
    return frames


def test_video_decodes_back_to_its_frames(tmp_path):
    frames = moving_frames()
    path = write_video(tmp_path / "cell" / "negative_sae_a+2_ep0_toward.mp4", frames, fps=8)
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no staging file left
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name in ("h264", "mpeg4") and stream.average_rate == 8
        decoded = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
    assert len(decoded) == len(frames) and decoded[0].shape == (224, 224, 3)
    assert np.abs(decoded[0].astype(int) - frames[0]).mean() < 4  # lossy, but close


def test_codec_is_h264_when_available():
    assert video_codec() == ("libx264" if "libx264" in av.codecs_available else "mpeg4")


def test_no_frames_or_odd_frames_are_refused(tmp_path):
    with pytest.raises(ValueError, match=r"a\.mp4: no frames to write; record frames"):
        write_video(tmp_path / "a.mp4", [])
    with pytest.raises(ValueError, match=r"frame 0 is uint8 \(223, 224, 3\)"):
        write_video(tmp_path / "b.mp4", [np.zeros((223, 224, 3), np.uint8)])
    with pytest.raises(ValueError, match=r"frames \[1\] differ"):
        write_video(tmp_path / "c.mp4", [np.zeros((8, 8, 3), np.uint8), np.zeros((8, 8, 3), np.float32)])
    assert not list(tmp_path.iterdir())
