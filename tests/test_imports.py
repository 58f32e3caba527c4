"""``import ldap_jax`` stays light: the core imports JAX and equinox only, and the heavy optional
dependencies load where they are used (diffrax in ``lj.reference``, matplotlib in
``ldap_jax.plotting``, optax in ``ldap_jax.control``).

A child process, because this worker imported all of them long ago.
"""

import subprocess
import sys

SCRIPT = """
import sys

import ldap_jax as lj

HEAVY = ("matplotlib", "diffrax", "scipy", "optax")
LAZY = ("ldap_jax.control", "ldap_jax.study", "ldap_jax.plotting")
loaded = [m for m in HEAVY + LAZY if m in sys.modules]
assert not loaded, f"import ldap_jax imported {loaded}"

# the subpackages are still attributes of the package, imported on first access
assert callable(lj.control.solve) and "ldap_jax.control" in sys.modules
assert "diffrax" not in sys.modules and "matplotlib" not in sys.modules, "lj.control imported them"
assert callable(lj.study.run_study) and callable(lj.reference)
assert "diffrax" not in sys.modules and "matplotlib" not in sys.modules
from ldap_jax import plotting

assert plotting is lj.plotting and "matplotlib" in sys.modules
assert {"control", "plotting", "study", "__version__"} <= set(dir(lj))
assert isinstance(lj.__version__, str) and lj.__version__
try:
    lj.no_such_name
except AttributeError as err:
    assert "no_such_name" in str(err)
else:
    raise AssertionError("lj.no_such_name did not raise AttributeError")
print("OK")
"""


def test_import_does_not_load_optional_dependencies():
    res = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.strip().endswith("OK")


def test_every_default_is_named_in_its_docstring():
    """Every public function and class of the package and its subpackages names each of its
    parameters with a default in its docstring (where the default is stated): a new argument
    cannot be added without documenting it."""
    import inspect
    import re

    import ldap_jax as lj
    from ldap_jax import control, plotting, study

    missing = []
    for mod_name, mod in {"lj": lj, "lc": control, "study": study, "plotting": plotting}.items():
        for name in getattr(mod, "__all__", None) or dir(mod):
            obj = getattr(mod, name)
            if name.startswith("_") or inspect.ismodule(obj) or not callable(obj):
                continue
            try:
                params = inspect.signature(obj).parameters.values()
            except (TypeError, ValueError):  # a builtin or an object without a signature
                continue
            doc = obj.__doc__ or ""
            for p in params:
                if p.default is not inspect.Parameter.empty and not p.name.startswith("_"):
                    if not re.search(rf"\b{re.escape(p.name)}\b", doc):
                        missing.append(f"{mod_name}.{name}({p.name}={p.default!r})")
    assert not missing, f"defaults not named in their docstrings: {missing}"
