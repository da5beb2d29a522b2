"""Where the persistent JAX compilation cache goes: the environment first, else the user cache directory."""

from kinetix.jaxcache import default_cache_dir


def test_kinetix_variable_wins_over_jax_variable(monkeypatch, tmp_path):
    monkeypatch.setenv("KINETIX_JAX_CACHE", str(tmp_path / "ours"))
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "jax"))
    assert default_cache_dir() == tmp_path / "ours"


def test_jax_variable_is_honoured(monkeypatch, tmp_path):
    monkeypatch.delenv("KINETIX_JAX_CACHE", raising=False)
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "jax"))
    assert default_cache_dir() == tmp_path / "jax"


def test_default_is_the_user_cache_outside_the_repository(monkeypatch, tmp_path):
    for variable in ("KINETIX_JAX_CACHE", "JAX_COMPILATION_CACHE_DIR", "XDG_CACHE_HOME"):
        monkeypatch.delenv(variable, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    assert default_cache_dir() == tmp_path / ".cache" / "kinetix" / "jax"
