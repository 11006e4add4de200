"""Phase 4: does each steering vector move the policy's actions, how far, and better than chance?"""

from steering_core.evaluate.settings import EvaluateSettings

__all__ = ["EvaluateSettings"]
