"""Triangle meshes of sheets with boundary electrodes, flat or on curved surfaces, generators,
geometric fields, and conservative interpolation of element fields between meshes."""

from ._fields import disc_fraction as disc_fraction
from ._fields import disc_fractions as disc_fractions
from ._fields import distance_to_segments as distance_to_segments
from ._fields import element_sample_points as element_sample_points
from ._fields import locate as locate
from ._fields import nearest_element as nearest_element
from ._fields import onto_sheet as onto_sheet
from ._fields import onto_surface as onto_surface
from ._fields import surface_distance as surface_distance
from ._generate import disc as disc
from ._generate import polygon as polygon
from ._generate import rectangle as rectangle
from ._interpolate import interpolate as interpolate
from ._interpolate import overlap_areas as overlap_areas
from ._interpolate import pixel_overlaps as pixel_overlaps
from ._interpolate import remap_matrix as remap_matrix
from ._mesh import Mesh as Mesh
from ._mesh import require_flat as require_flat
from ._read import read as read
from ._surface import cylinder_patch as cylinder_patch
from ._surface import sphere_cap as sphere_cap
from ._topology import centroid_distances as centroid_distances
from ._topology import element_adjacency as element_adjacency
