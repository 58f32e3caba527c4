import jax

import ldap_jax as lj

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_numpy_rank_promotion", "raise")


def pytest_runtest_teardown(item, nextitem):
    # Each compiled program holds hundreds of memory mappings on XLA's CPU backend; a test worker
    # that compiles a few hundred programs would cross vm.max_map_count and crash inside XLA.
    lj.trim_compilation_cache(0.4)
