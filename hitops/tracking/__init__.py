"""Reference-band phase-wrap tracking: the three trackers of ``hitops calibrate`` and their theory.

One interface (:mod:`.base`: ``WrapTracker`` and the types it passes, ``ReferenceGrid``
in, ``ChunkTracking`` out, split into one ``BatchWraps`` per baseline batch of the
transfer) with one module per tracker: :mod:`.count` (the paper's step > pi rule), :mod:`.smooth` (smoothed
unit phasor, gap bridging, jump detection) and :mod:`.antenna` (wraps tracked
per antenna), each with its numba kernels beside it (:mod:`.smooth_kernel`,
:mod:`.antenna_kernel`); the shared parts: :mod:`.options` (checks, resolved
setup), :mod:`.grid` (regular time grid), :mod:`.windows` (per-sample SNR and
windows), :mod:`.state` / :mod:`.antenna_state` (what carries across chunks,
confidence numbers), :mod:`.factory` (a tracker by name).  Offline and
theory: :mod:`.modes` (whole tracks at once), :mod:`.theory`,
:mod:`.stations`.  See docs/tracking.md.
"""
