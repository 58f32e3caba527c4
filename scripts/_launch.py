"""The options of a run of several JAX processes for the scripts (sweep.py, optimize.py).

They are ``ldap_jax.launch``'s (``add_arguments``, ``check_arguments``), read here from the module's
file: importing the package starts JAX, and the scripts check their flags before that (a bad flag
fails at once, not after seconds of imports).
"""

import importlib.util
import os


def launch_options():
    """``ldap_jax.launch``'s functions, without importing the package."""
    package = importlib.util.find_spec("ldap_jax")
    path = os.path.join(os.path.dirname(package.origin), "launch.py")
    spec = importlib.util.spec_from_file_location("ldap_jax_launch_options", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
