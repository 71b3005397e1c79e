"""diffeit's hardware module: measured frames from a serial port into a frames file.

- `hw.frame`: the binary frame format (sync marker, version, counter, timestamp, layout,
  values, CRCs) and the text lines of simple boards; `encode_frame`, `encode_text_line`; the
  layout ids `LAYOUT_DECLARED`, `LAYOUT_ADJACENT`, `LAYOUT_ADJACENT_FULL`, `LAYOUT_OPPOSITE`.
- `hw.parser`: `BinaryParser`, `TextParser`: streaming, resynchronising, counting every drop
  (`DropStatistics`); the resynchronisation rule is in its docstring.
- `hw.serial_port`: `SerialSource`, acquisition with pyserial (port names and URLs,
  reconnection, host timestamps, an iterator and a callback API).
- `hw.emulator`: `Emulator`, a device on a pseudo-terminal with fault injection (the kinds
  `FAULT_KINDS`) and a ground-truth log.
- `hw.recorder`: `Recorder`, frames appended to a diffeit frames file as they arrive (HDF5,
  SWMR), so that a kill loses at most the frame in flight; `read_recorded_frames`.

`hw` depends on `diffeit.io` (and the protocols it stores) only.
"""

from .emulator import FAULT_KINDS as FAULT_KINDS
from .emulator import Emulator as Emulator
from .emulator import Fault as Fault
from .emulator import FaultRates as FaultRates
from .emulator import plan_faults as plan_faults
from .frame import LAYOUT_ADJACENT as LAYOUT_ADJACENT
from .frame import LAYOUT_ADJACENT_FULL as LAYOUT_ADJACENT_FULL
from .frame import LAYOUT_DECLARED as LAYOUT_DECLARED
from .frame import LAYOUT_OPPOSITE as LAYOUT_OPPOSITE
from .frame import Frame as Frame
from .frame import encode_frame as encode_frame
from .frame import encode_text_line as encode_text_line
from .frame import layout_matches as layout_matches
from .frame import layout_of as layout_of
from .frame import layout_protocol as layout_protocol
from .parser import BinaryParser as BinaryParser
from .parser import DropStatistics as DropStatistics
from .parser import TextParser as TextParser
from .recorder import Recorder as Recorder
from .recorder import read_recorded_frames as read_recorded_frames
from .recorder import recorded_statistics as recorded_statistics
from .serial_port import DeviceLost as DeviceLost
from .serial_port import SerialSource as SerialSource
