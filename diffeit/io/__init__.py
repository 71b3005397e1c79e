"""Frames on disk: one HDF5 schema for simulated, recorded and reconstructed data, and readers
of other formats (EIDORS .mat files).

`diffeit.io` is a leaf: it uses the data modules `diffeit.protocol` and `diffeit.mesh` only
(never the forward model, the solvers or the command line), so the hardware module can depend
on it alone.

In memory a data set is a `Recording` (frames, times, protocol, reference, mesh or geometry,
provenance, images, and what a reading is: signed, or a magnitude). `write_frames(path,
recording)` writes one file (refusing to replace an existing file unless `overwrite=True`),
`append_frames(path, frames, times)` grows it (a recorder), `read_frames(path)` reads and
validates it. Readers of other recordings, each mapping the frames to a diffeit protocol:
`read_eidors_mat(path, variable)` (EIDORS-style MATLAB frames, real or complex, with or
without the readings on driven electrodes), `read_openeit(path)` (OpenEIT text logs, its
opposition layout, magnitudes), `read_csv(path)` (one frame a row).

The frames file (HDF5, schema "diffeit.frames", version 2):

```
/                    attributes:
                       schema = "diffeit.frames", schema_version = 2 (int)
                       diffeit_version (str), created_utc (ISO 8601, UTC), source (str)
                       metadata (str): free-form user metadata as JSON
/frames              (T, n_meas) float64, attributes units: "V" (or "arbitrary": device units)
                     and readings: "signed" (the protocol's sign; read as such when absent) or
                     "magnitude" (|V|, never negative: the instrument loses the sign);
                     resizable along T (maxshape (None, n_meas)), chunked by 64 frames
/times               (T,) float64, attribute units = "s"; resizable like frames
/reference           (n_meas,) float64, units and readings as frames         [optional]
/protocol/drive      (n_drives, L) float64: current into each electrode per drive, in multiples
                     of the model's drive current (positive into the sheet)
/protocol/measure    (n_meas, L) float64: the weights of each reading, sum_l w_l U_l
/protocol/drive_index  (n_meas,) int64: the drive of each reading, drive by drive
/mesh/nodes          (N, 2) float64 ((N, 3): a surface in 3D), attribute units = "m"  [optional]
/mesh/triangles      (E, 3) int64, counter-clockwise (in 3D consistently oriented)
/mesh/electrode_nodes   (K,) int64: every electrode's boundary node chain, concatenated
/mesh/electrode_offsets (L + 1,) int64: electrode l is electrode_nodes[offsets[l]:offsets[l+1]]
/geometry            group whose attributes describe the sheet for a generator     [optional]
                     (kind = "disc" | "rectangle" | "polygon", and that generator's keyword
                     arguments, lengths in metres, e.g. n_electrodes, electrode_width, h, radius)
/images              (T, E) float64 on /mesh, attributes units = "S/sq" and     [optional]
                     quantity = "conductivity change" | "conductivity"
/committed_frames    (1,) int64: the frames (and times) a recorder committed; rows [optional]
                     beyond it are the frame in flight when it was stopped, and are not read
/acquisition/        written by hw.Recorder (counters, device times, drop statistics) [optional]
```

`read_frames` reports a recorder's drop statistics (`/acquisition/drops`) in the provenance
metadata, as `drop_statistics`; `drop_statistics` reads them alone from an open file.

n_meas is the protocol's number of readings and L its number of electrodes. Frames are in the
protocol's order and sign (for `adjacent(16)`, EIDORS's). Files are written in the HDF5 1.10
format, which single-writer/multiple-reader (SWMR) access needs; `read_frames` reads a file a
recorder is still writing, or was writing when it was killed, through SWMR access.

Damage is refused, never read as data: every array dataset carries a Fletcher-32 checksum
(every scalar sits in its checksummed object header), HDF5 1.10's metadata carries checksums,
and a truncated file is recognised from its superblock before HDF5 reads it (`open_checked`).
Every reader raises a `ValueError` naming the file for a damaged one, within moments. Version 1
(written before checksums; committed_frames of shape ()) reads with a `NoChecksumWarning`.
`open_checked`, `read_checked`, `create_checked` and `write_atomically` are the discipline every diffeit HDF5
file follows (frames, fits, recorders): use them for files of your own.
"""

from ._checked import NoChecksumWarning as NoChecksumWarning
from ._checked import create_checked as create_checked
from ._checked import open_checked as open_checked
from ._checked import read_attributes as read_attributes
from ._checked import read_checked as read_checked
from ._checked import write_atomically as write_atomically
from ._checked import write_attributes as write_attributes
from ._csv import read_csv as read_csv
from ._eidors import read_eidors_mat as read_eidors_mat
from ._hdf5 import CHUNK_ROWS as CHUNK_ROWS
from ._hdf5 import SCHEMA as SCHEMA
from ._hdf5 import SCHEMA_VERSION as SCHEMA_VERSION
from ._hdf5 import append_frames as append_frames
from ._hdf5 import drop_statistics as drop_statistics
from ._hdf5 import read_frames as read_frames
from ._hdf5 import write_frames as write_frames
from ._openeit import read_openeit as read_openeit
from ._presses import Presses as Presses
from ._presses_csv import read_presses as read_presses
from ._recording import Recording as Recording
from ._recording import mesh_from_geometry as mesh_from_geometry
