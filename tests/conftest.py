"""Session-wide test settings: offline hub access, quiet telemetry, a private digest cache."""

import os
import tempfile

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
# large files' digests are remembered across processes; tests keep theirs out of the user cache
os.environ.setdefault("LATENT_STEERING_DIGEST_CACHE", tempfile.mkdtemp(prefix="latent-steering-digests-"))
