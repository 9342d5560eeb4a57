"""jaxsh: signal-processing inverse rendering in JAX (pure forward maths).

Conventions are in docs/conventions.md and the README; every public function states
the ones it uses.
"""

from ._checks import error_if as error_if
from ._compile import compile_options as compile_options, jit as jit
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
from ._convolution import (
    complex_to_real_coeffs as complex_to_real_coeffs,
    convolve as convolve,
    irradiance as irradiance,
    real_to_complex_coeffs as real_to_complex_coeffs,
)
from ._spectra import (
    lambertian_spectrum as lambertian_spectrum,
    legendre_p as legendre_p,
    microfacet_spectrum as microfacet_spectrum,
    mirror_spectrum as mirror_spectrum,
    phong_spectrum as phong_spectrum,
    phong_spectrum_gaussian as phong_spectrum_gaussian,
    radial_spectrum as radial_spectrum,
    recoverable_orders as recoverable_orders,
    torrance_sparrow_spectrum as torrance_sparrow_spectrum,
)
from ._lightfield import (
    mirror_brdf_coefficients as mirror_brdf_coefficients,
    brdf_incident_coefficients as brdf_incident_coefficients,
    brdf_sh_coefficients as brdf_sh_coefficients,
    factorize_light_field as factorize_light_field,
    light_field_basis as light_field_basis,
    light_field_coefficients as light_field_coefficients,
    reflect_sh as reflect_sh,
)
from ._reference import reflect_quadrature as reflect_quadrature
from ._reflectance import (
    cook_torrance as cook_torrance,
    fresnel_dielectric as fresnel_dielectric,
    fresnel_normalized as fresnel_normalized,
    half_angle as half_angle,
    half_vector as half_vector,
    lafortune as lafortune,
    lambertian as lambertian,
    local_directions as local_directions,
    mirror_direction as mirror_direction,
    oren_nayar as oren_nayar,
    phong as phong,
    phong_transfer as phong_transfer,
    reflect as reflect,
    rusinkiewicz_angles as rusinkiewicz_angles,
    rusinkiewicz_directions as rusinkiewicz_directions,
    tangent_frame as tangent_frame,
    torrance_sparrow as torrance_sparrow,
    uvw as uvw,
    uvw_from_directions as uvw_from_directions,
    ward_isotropic as ward_isotropic,
)
from ._microfacet import cook_torrance_smith as cook_torrance_smith, ggx as ggx
from ._lighting import (
    directional_light_sh as directional_light_sh,
    disk_energy as disk_energy,
    disk_light_sh as disk_light_sh,
    filter_lighting_microfacet as filter_lighting_microfacet,
    is_fast_source as is_fast_source,
    split_disk_sources as split_disk_sources,
)
from ._model import Lighting as Lighting, TorranceSparrow as TorranceSparrow
from ._render import Components as Components, render_practical as render_practical, render_reference as render_reference
from ._camera import (
    OrthographicCamera as OrthographicCamera,
    PinholeCamera as PinholeCamera,
    camera_rays as camera_rays,
    look_at as look_at,
)
from ._gbuffer import (
    GBuffer as GBuffer,
    normal_map_gbuffer as normal_map_gbuffer,
    sphere_gbuffer as sphere_gbuffer,
    visibility_weighted_irradiance as visibility_weighted_irradiance,
)
from ._raycast import (
    directional_visibility as directional_visibility,
    embree_available as embree_available,
    hemisphere_quadrature as hemisphere_quadrature,
    mesh_gbuffer as mesh_gbuffer,
    reflected_visibility as reflected_visibility,
    visibility_sh as visibility_sh,
)
from ._practical import PracticalTerms as PracticalTerms, practical_terms as practical_terms
from ._rbf import (
    RBFModel as RBFModel,
    rbf_auto_chunk as rbf_auto_chunk,
    rbf_check_samples as rbf_check_samples,
    rbf_evaluate as rbf_evaluate,
    rbf_fit as rbf_fit,
    rbf_solve as rbf_solve,
    sbrdf_points as sbrdf_points,
    scaled_distances as scaled_distances,
)
