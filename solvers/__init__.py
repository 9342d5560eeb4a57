"""solvers: inverse rendering on top of jaxsh (R&H 2001 sec. 6; Zickler et al. 2006).

Results are equinox Modules with the estimate, a `Status`, iterations, RMS
residual and standard errors; see docs/results.md.
"""

from ._results import Solution as Solution, SolveError as SolveError, Status as Status, status_name as status_name
from ._data import (
    Lighting as Lighting,
    Observations as Observations,
    TorranceSparrow as TorranceSparrow,
    observations as observations,
    practical_terms_for as practical_terms_for,
    predict as predict,
)
from ._brdf import MU_BOUNDS as MU_BOUNDS, SIGMA_BOUNDS as SIGMA_BOUNDS, BRDFResult as BRDFResult, fit_brdf as fit_brdf
from ._brdf_sh import BRDFSHResult as BRDFSHResult, fit_brdf_sh as fit_brdf_sh, predict_brdf_sh as predict_brdf_sh
from .synthetic import (
    SyntheticCapture as SyntheticCapture,
    default_sources as default_sources,
    sphere_capture as sphere_capture,
    view_cameras as view_cameras,
)
from ._sharing import SharingFit as SharingFit, fit_sharing as fit_sharing
from ._lighting import (
    DualLightingResult as DualLightingResult,
    LightingResult as LightingResult,
    inverse_lighting as inverse_lighting,
    inverse_lighting_dual as inverse_lighting_dual,
)
from ._factorize import (
    FactorizationResult as FactorizationResult,
    SourceEstimate as SourceEstimate,
    factorize as factorize,
    find_source as find_source,
)
from ._sharing import (
    DichromaticReflectance as DichromaticReflectance,
    OneImageReflectance as OneImageReflectance,
    RBFReflectance as RBFReflectance,
    Samples as Samples,
    fit_dichromatic as fit_dichromatic,
    fit_homogeneous as fit_homogeneous,
    fit_one_image as fit_one_image,
    fit_sbrdf as fit_sbrdf,
    reflectance_samples as reflectance_samples,
    render_rbf as render_rbf,
)
from ._sharing_study import sharing_tradeoff as sharing_tradeoff
from ._scale import (
    fit_many as fit_many,
    pad_observations as pad_observations,
    pixel_mesh as pixel_mesh,
    shard_observations as shard_observations,
)
