"""Phase 2, capture: π0.5 residuals at the prompt tokens, stored in shards, sliced by concept.

Modules: `settings` (what to capture, checked inputs), `identity` (what rows depend on), `frames`
(DataLoader of LeRobot frames), `loop` (the capture), `shards` (the on-disk format), `slicing`.
"""

from steering_core.capture.loop import CaptureResult, capture
from steering_core.capture.settings import CaptureSettings

__all__ = ["CaptureResult", "CaptureSettings", "capture"]
