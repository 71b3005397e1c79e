"""Fitting skins to frames by gradient optimisation through the forward and memory models.

Real skins are not uniform, and they remember earlier touches. `diffeit.fit` estimates both from
recorded frames:

- `background`: the background conductivity map (and contact impedances, and a gain per reading
  for instruments that have one) from untouched reference frames;
- `memory`: the memory model's parameters and the memoryless stimulus from a sequence of
  relative-change images, per element, in image space;
- `correct_memory`: the causal correction of images with known memory parameters (live use);
- `joint`: background, contact impedances, memory parameters and per-frame stimulus images
  together, with every frame's misfit through the forward model.

Every fit returns an `equinox.Module` with a `result` code (`diffeit.results.RESULTS`) and takes
`throw=`.
"""

from ._background import BackgroundFit as BackgroundFit
from ._background import background as background
