"""What a user reads: every result code has a message, success included."""

import ldap_jax as lj


def test_every_result_has_a_message():
    success = lj.RESULTS[lj.RESULTS.successful]
    assert success.startswith("successful"), success
    for name in ("nonfinite", "singular", "not_converged", "diverged", "invalid_input"):
        message = lj.RESULTS[getattr(lj.RESULTS, name)]
        assert message and message != success, name
