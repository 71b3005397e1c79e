"""Triangle meshes of sheets with boundary electrodes, generators, and geometric fields."""

from ._fields import disc_fraction as disc_fraction
from ._generate import disc as disc
from ._mesh import Mesh as Mesh
