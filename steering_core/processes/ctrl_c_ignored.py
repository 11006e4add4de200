"""Imported for its effect, first, by processes that must ignore Ctrl-C from their first imports on (the frame
workers' forkserver, `capture.frames.WORKER_PRELOAD`): a light module, so the window before it is short."""

from steering_core.processes import ignore_ctrl_c

ignore_ctrl_c()
