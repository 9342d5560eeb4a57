"""Synthetic test and demo scenes: known geometry, lighting and reflectance, rendered by jaxsh.

**These are not solvers.** They build inputs with a known answer, for the
`jaxsh demo` command, the notebooks, the tests and the benchmarks; the
inverse problems they feed live in `solvers` itself.

* Sphere captures (R&H 2001 fig. 11 style; `_sphere.py`): `sphere_capture`
  renders views of a unit sphere with the full Torrance–Sparrow BRDF under
  `default_sources()` seen by `view_cameras(...)`, into a `SyntheticCapture`;
  `procedural_sky` is an HDR lat-long sky with a sun lobe.
* Reflectance-sharing scenes (Zickler et al. 2006 secs. 6.1, 7.1, 8.4;
  `_sharing_scenes.py`): sphere geometry, light sets, reference BRDFs, the
  parametric baselines (`fit_ward`, `fit_lafortune`), per-pixel
  "no sharing" interpolation and the paper's protocols.

`solvers.sphere_capture`, `solvers.SyntheticCapture`,
`solvers.default_sources` and `solvers.view_cameras` are re-exports of the
names here.
"""

from ._sphere import (
    SyntheticCapture as SyntheticCapture,
    default_sources as default_sources,
    procedural_sky as procedural_sky,
    sphere_capture as sphere_capture,
    view_cameras as view_cameras,
)
from ._sharing_scenes import (
    VIEW as VIEW,
    ParametricBRDF as ParametricBRDF,
    albedo_texture as albedo_texture,
    cone_lights as cone_lights,
    dichromatic_components as dichromatic_components,
    fit_lafortune as fit_lafortune,
    fit_ward as fit_ward,
    hemisphere_protocol as hemisphere_protocol,
    homogeneous_protocol as homogeneous_protocol,
    metallic_brdf as metallic_brdf,
    no_sharing_predict as no_sharing_predict,
    one_image_protocol as one_image_protocol,
    oren_nayar_brdf as oren_nayar_brdf,
    relative_rms as relative_rms,
    render_images as render_images,
    sphere_geometry as sphere_geometry,
    theta_d_lights as theta_d_lights,
    valid_masks as valid_masks,
    varying_cook_torrance as varying_cook_torrance,
)
