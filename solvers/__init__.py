"""Inverse problems built on jaxsh."""
from ._sharing import SharingFit as SharingFit, fit_sharing as fit_sharing
