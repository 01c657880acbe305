"""The n0 offset step of PWC and CWU: which 2 pi eps k each scan or segment carries.

PWC counts reference wraps from 0 at the first sample, so its output keeps a
constant 2 pi eps n0 per scan or tracking segment; the step measures it against
an offset reference (a calibrated column, or a model) and adds the integer back.
One module per job:

* :mod:`.step`: the step as the pipeline runs it (:func:`~.step.solve_offsets`
  from the first pass's sums to an :class:`~.step.OffsetSolution`; the shift of
  a kept output);
* :mod:`.baseline`: the per-baseline offsets, one circular mean and the nearest
  lattice point (:func:`~.baseline.choose_offset`; count and smooth trackers);
* :mod:`.antenna`: the antenna tracker's integers per antenna and segment, one
  lattice solve over every baseline (and both parallel hands, :mod:`.hands`);
* :mod:`.lattice`: the integer lattice solver itself, pure;
* :mod:`.table` and :mod:`.channel_lattice`: the same step on a table's transferred
  solutions (``--reference-table``): one integer per antenna, receptor and segment,
  each channel keeping its own sum.

Across a target window's channels (issue 26) every sum is one per channel and a
candidate k is scored by Re(sum_j z_j exp(-2 pi i R_j k)) (a
:class:`~.baseline.WindowRatios`): the channels tell k from k + 43, which one
channel cannot (docs/wideband.md, "The n0 step across the channels").

The first pass's per-segment sums and the shift are numba kernels in
:mod:`hitops.kernels.segments`.
"""
