"""Prefect flows of the pipeline.

Prefect's logging setup leaves the root logger at WARNING and only adds its handlers to the loggers named in
PREFECT_LOGGING_EXTRA_LOGGERS (prefect.yaml names `steering_core`), so the library's INFO lines (progress
included) would never reach a worker's output or the UI: its logger is set to INFO here, unless set already.
"""

import logging

LIBRARY_LOGGER = "steering_core"

if logging.getLogger(LIBRARY_LOGGER).level == logging.NOTSET:
    logging.getLogger(LIBRARY_LOGGER).setLevel(logging.INFO)
