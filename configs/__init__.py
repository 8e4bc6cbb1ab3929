"""mapkit's presets and configs, installed as the package ``mapkit.configs``: read them with :mod:`mapkit.core.presets`."""
