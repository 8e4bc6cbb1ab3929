"""mapkit: drive logs to maps, image databases, triplet patches and place-recognition indexes.

The library is layered as in evo: ``mapkit.core.geometry`` and ``mapkit.core.types`` are pure numpy/scipy,
``mapkit.core.geodesy`` wraps pyproj, ``mapkit.io`` holds every reader and writer, and ``mapkit.cli``
only parses arguments and calls the library.
"""

__version__ = "0.1.0"
