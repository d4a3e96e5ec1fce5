"""The presets: this folder installs as the package ``neural_brdf.configs`` (pyproject.toml).

A regular package (this file) rather than a namespace one, so that ``importlib.resources``
finds it in an editable install too.  Read it through ``neural_brdf.presets``.
"""
