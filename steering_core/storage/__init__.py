"""Local files every phase writes and reads: atomic writes (`fileio`), file digests (`digests`), NaN/Inf checks
(`finite`), validated JSON (`schema`), per-output lock files (`locks`) and where a bucket is mirrored on disk
(`mirrors`). Object storage itself: `steering_core.remote`."""
