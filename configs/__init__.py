"""The configuration presets (YAML), installed as the package ``slam.presets`` (see pyproject.toml):
``dynslam run SEQ -c NAME`` finds ``NAME.yaml`` here from any folder."""
