"""Scenes and effects: describe an experiment on a skin and simulate exactly what it calls for.

A `Scene` holds a `Skin` (sheet, electrodes, contact impedance, protocol), a `Background`
(uniform, per region or a function; S/sq), `Touch`es (footprints `Disc`, `Ellipse`, `Polygon`
with smooth edges; time courses `Press`, `Ramp`, `Path`), a frame rate and duration, and the
effects to simulate (`EFFECTS`): the skin's memory (`MemoryParameters`), measurement noise
(`MeasurementNoise` of a `Noise`), common-mode drift (`CommonModeDrift`), contact impedance
drift (`ContactDrift`), open electrodes (`OpenElectrodes`), electrode position error
(`ElectrodePositionError`), readout mixing (`ReadoutMixing`: each reading mixes in other
electrodes' potentials, `diffeit.readout.Readout`) and reading gains (`ReadingGains`). Scenes
load from and save to TOML (`Scene.from_toml`, `Scene.to_toml`); `example(name)` gives the
shipped scenes of `EXAMPLES`.

`simulate(scene)` runs the `pipeline` of the stages the scene declares and returns a
`Simulation` (frames, times, reference, ground truth), saved to and read from the frames file
of `diffeit.io` (`Simulation.save`, `read_simulation`). Each effect is also a pure function of
its own (`stimulus`, `memory_response`, `add_noise`, `add_drift`, `contact_impedance`,
`open_electrodes`, `pressure_to_change`) for use in fitting code.
"""

from ..memory import MemoryParameters as MemoryParameters
from ..memory import MemoryState as MemoryState
from ..memory import advance as advance
from ..memory import apply_stimulus as apply_stimulus
from ..memory import bare_skin as bare_skin
from ..memory import initial_state as initial_state
from ..memory import integrate_memory as integrate_memory
from ..memory import memory_response as memory_response
from ..memory import over_foam as over_foam
from ..memory import read_response as read_response
from ._background import Background as Background
from ._background import Region as Region
from ._effects import EFFECT_NAMES as EFFECT_NAMES
from ._effects import EFFECTS as EFFECTS
from ._instrument import NOISE_LEVELS as NOISE_LEVELS
from ._instrument import OPEN_FACTOR as OPEN_FACTOR
from ._instrument import CommonModeDrift as CommonModeDrift
from ._instrument import ContactDrift as ContactDrift
from ._instrument import ElectrodePositionError as ElectrodePositionError
from ._instrument import MeasurementNoise as MeasurementNoise
from ._instrument import Noise as Noise
from ._instrument import OpenElectrodes as OpenElectrodes
from ._instrument import ReadingGains as ReadingGains
from ._instrument import ReadoutMixing as ReadoutMixing
from ._instrument import add_drift as add_drift
from ._instrument import add_noise as add_noise
from ._instrument import contact_impedance as contact_impedance
from ._instrument import lost_readings as lost_readings
from ._instrument import open_contact_impedance as open_contact_impedance
from ._instrument import open_electrodes as open_electrodes
from ._scene import EXAMPLES as EXAMPLES
from ._scene import Scene as Scene
from ._scene import example as example
from ._scene import example_path as example_path
from ._shapes import Disc as Disc
from ._shapes import Ellipse as Ellipse
from ._shapes import Polygon as Polygon
from ._shapes import shape_fraction as shape_fraction
from ._simulate import Simulation as Simulation
from ._simulate import Stage as Stage
from ._simulate import pipeline as pipeline
from ._simulate import read_simulation as read_simulation
from ._simulate import simulate as simulate
from ._skin import Skin as Skin
from ._time_courses import Path as Path
from ._time_courses import Press as Press
from ._time_courses import Ramp as Ramp
from ._touches import FoamStack as FoamStack
from ._touches import Touch as Touch
from ._touches import pressure_to_change as pressure_to_change
from ._touches import project_to_surface as project_to_surface
from ._touches import stimulus as stimulus
from ._touches import touch_field as touch_field
