"""Process-wide JAX settings jaxslam relies on.

SLAM cost functions need float64: pose graphs with thousands of poses lose whole
digits of the final cost in float32. Importing :mod:`jaxslam` turns on
``jax_enable_x64``; arrays created before that import keep their dtype.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)
