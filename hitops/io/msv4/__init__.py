"""MSv4 processing sets (xradio's zarr v3 stores): the second backend of hitops/io (issue 37).

* ``store.py``: what a path holds (:func:`is_processing_set`), the checked
  :class:`ProcessingSetStore` (foreign, half-written, other-schema stores refused);
* ``layout.py``: the set's metadata with the MSv2 ids recovered
  (:func:`read_layout`); :func:`hitops.io.metadata.read_metadata` turns it into the
  same ``SetMetadata`` as the Measurement Set the store was converted from;
* ``rows.py``: a partition's rows chunk by chunk, as MSv2 columns (:class:`PartitionReader`);
* ``data_group.py``: a new data group staged, written and registered last
  (:class:`DataGroupWriter`).
* ``columns.py``: MSv2 column names in terms of data groups (DATA -> ``base``,
  CORRECTED_DATA -> ``corrected``; FLAG, WEIGHT of the band's group), for calibrate;
* ``group_rows.py``: a (field, window) group read as calibrate reads a Measurement Set's
  (:class:`~hitops.io.msv4.group_rows.PartitionSource`, behind
  :func:`hitops.io.read.open_for_reading`); calibrate's writer of new data groups is
  hitops/calibrate/output_msv4.py;
* ``uvfits_rows.py``: a data group as the UVFITS writer's rows and setup
  (:func:`hitops.io.uvfits.export_uvfits` on a store);
* ``casa_view.py``: the store's subtables as an empty Measurement Set v2, from which CASA
  lays out ``--caltable``'s table (hitops/io/caltable.py).

zarr and xradio come with the ``msv4`` extra (``pip install 'hitops[msv4]'``); they are
imported only when a processing set is opened.  docs/msv4.md says what is measured.
"""

from .data_group import DataGroupWriter, GroupVariables
from .layout import ProcessingSetLayout, read_layout
from .rows import PartitionReader, PartitionRows
from .store import ProcessingSetStore, is_processing_set, is_zarr_store, open_store

__all__ = ["DataGroupWriter", "GroupVariables", "ProcessingSetLayout", "read_layout",
           "PartitionReader", "PartitionRows", "ProcessingSetStore", "is_processing_set",
           "is_zarr_store", "open_store"]
