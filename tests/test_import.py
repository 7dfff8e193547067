def test_envs_live_in_the_plugin_namespace():
    import importlib.util
    import sb3_spikeplastic.envs  # noqa: F401
    assert importlib.util.find_spec("envs") is None
