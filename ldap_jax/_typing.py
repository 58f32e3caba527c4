"""Type aliases of the public API.

``ArrayLike`` is what the library accepts where it takes numbers: JAX and NumPy arrays, scalars,
and (nested) Python lists and tuples of numbers, which it converts with ``jnp.asarray`` after
checking them (``jaxtyping.ArrayLike`` alone would reject lists under a run-time type checker).
"""

from jaxtyping import ArrayLike as _ArrayLike

ArrayLike = _ArrayLike | list | tuple
