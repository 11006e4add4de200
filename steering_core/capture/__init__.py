"""Phase 2, capture: π0.5 residuals at the prompt tokens, stored in shards, sliced by concept.

Modules: `settings` (what to capture, checked inputs), `run_identity` (what rows depend on), `frames`
(DataLoader of LeRobot frames), `selected_rows` (the forward of the selected rows only), `loop` (the
capture), `action_rows` (decision and adaRMS rows), `shards` (the on-disk format), `slicing`.
"""

from steering_core.capture.loop import CaptureResult, capture
from steering_core.capture.settings import CaptureSettings

__all__ = ["CaptureResult", "CaptureSettings", "capture"]
