"""Fitting skins to frames by gradient optimisation through the forward and memory models.

Real skins are not uniform, and they remember earlier touches. `diffeit.fit` estimates both from
recorded frames:

- `background`: the background conductivity map (and contact impedances, and a gain per reading
  for instruments that have one) from untouched reference frames;
- `memory`: the memory model's parameters and the memoryless stimulus from a sequence of
  relative-change images, per element, in image space;
- `correct_memory`: the causal correction of images with known memory parameters (live use);
- `ordered_modes`: memory parameters with the quicker recovery mode named fast (the model
  treats both alike; every fit reports this order);
- `joint`: background, contact impedances, memory parameters and per-frame stimulus images
  together, with every frame's misfit through the forward model; `JointFit.save` and `load`
  keep a fit, `joint(..., initial=fit)` resumes it, and `joint(..., on_step=...)` hands out
  the fit so far at every step (`JointProgress`: to save, and resume after a kill);
- `JointImaging`: the joint fit as a reconstruction solver (`diffeit.inverse.AbstractSolver`):
  settings on the object, `solve(readings)` returns a `diffeit.inverse.Solution` holding every
  frame's conductivity change;
- `memory_uncertainty`: how well the frames determine a joint fit's memory parameters (standard
  errors and correlations, the Cramer-Rao bound at the fit);
- `memory_from_presses`: the memory parameters from images of labelled presses (footprints and
  holds known, depths fitted), with their standard errors;
- `memory_from_press_readings`: the same from the session's readings, each press's signature
  learned from its own frames: what `diffeit.calibrate` uses.

Every fit returns an `equinox.Module` with a `result` code (`diffeit.results.RESULTS`) and takes
`throw=`.
"""

from ._background import BackgroundFit as BackgroundFit
from ._background import background as background
from ._joint import JointFit as JointFit
from ._joint import JointImaging as JointImaging
from ._joint import JointParameters as JointParameters
from ._joint import JointPriors as JointPriors
from ._joint import JointProblem as JointProblem
from ._joint import JointProgress as JointProgress
from ._joint import JointSettings as JointSettings
from ._joint import joint as joint
from ._joint import load as load
from ._memory import MemoryFit as MemoryFit
from ._memory import correct_memory as correct_memory
from ._memory import correct_memory_step as correct_memory_step
from ._memory import memory as memory
from ._memory import ordered_modes as ordered_modes
from ._presses import memory_from_press_readings as memory_from_press_readings
from ._presses import memory_from_presses as memory_from_presses
from ._uncertainty import MemoryUncertainty as MemoryUncertainty
from ._uncertainty import memory_uncertainty as memory_uncertainty
