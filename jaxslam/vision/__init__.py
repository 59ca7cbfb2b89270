"""Vision front end: low-light image enhancement (ABA-CLAHE, SPEC §3.1) as JAX array ops.

Public surface: :func:`aba_clahe`, :func:`clahe`, :func:`equalize_hist`,
:func:`gamma_correct`, :func:`aba_curve`.
"""

from ._enhance import aba_clahe, aba_curve, clahe, equalize_hist, gamma_correct

__all__ = ["aba_clahe", "aba_curve", "clahe", "equalize_hist", "gamma_correct"]
