"""Imported for its effect, first, by a child process that has no other hook at its start (the frame workers'
forkserver, `capture.frames.WORKER_PRELOAD`): from here on it ignores Ctrl-C, which its parent handles, and dies
with its parent, not minutes later once its own imports end. A light module, so the window before it is short."""

from steering_core.processes import die_with_parent, ignore_ctrl_c

ignore_ctrl_c()
die_with_parent()
