"""The bundled scenarios (TOML), at the top of the repository where a user reads and copies them;
pancam_graph/scenarios links here, and the wheel carries them as this package's data."""
