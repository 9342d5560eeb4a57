"""jaxsh: signal-processing inverse rendering in JAX (pure forward maths).

Conventions are in DESIGN.md and the README; every public function states
the ones it uses.
"""

from ._indexing import (
    num_coeffs as num_coeffs,
    real_to_complex_matrix as real_to_complex_matrix,
    sh_degree_order as sh_degree_order,
    sh_degrees as sh_degrees,
    sh_index as sh_index,
    sh_lambda as sh_lambda,
    sh_orders as sh_orders,
)
from ._sh import complex_sh as complex_sh, real_sh as real_sh

__version__ = "0.1.0"
from ._grids import (
    angular_map_directions as angular_map_directions,
    fejer1_weights as fejer1_weights,
    gauss_legendre_grid as gauss_legendre_grid,
    latlong_angles as latlong_angles,
    latlong_directions as latlong_directions,
    latlong_weights as latlong_weights,
)
from ._transforms import (
    fit_sh as fit_sh,
    project_latlong as project_latlong,
    synthesize_latlong as synthesize_latlong,
)
from ._rotation import (
    rotate_sh as rotate_sh,
    rotation_from_euler_zyz as rotation_from_euler_zyz,
    wigner_D as wigner_D,
    wigner_D_blocks as wigner_D_blocks,
    wigner_d_y as wigner_d_y,
)
