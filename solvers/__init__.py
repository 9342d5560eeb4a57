"""Inverse problems built on jaxsh."""
from ._sharing import SharingFit as SharingFit, fit_sharing as fit_sharing
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
)
