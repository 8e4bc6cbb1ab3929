"""mapkit: drive logs to maps, image databases, triplet patches and place-recognition indexes.

One subpackage per stage, in the order the data flows: ``core`` (types, geometry, geodesy, configs,
run I/O, the ``Workspace``), ``io`` (readers and writers), ``synth`` (the synthetic town),
``mapping`` (one session: ``mapkit build``), ``multisession`` (``mapkit align``), ``places`` and
``retrieval`` (descriptors, triplets and the deployable indexes), ``learning``, ``localization``
and ``deploy``, then ``evaluation``, ``report`` and ``pipelines``; ``mapkit.cli`` only parses
arguments. Imports point down that list only (docs/architecture.md).
"""

from mapkit.core.blas import pin_openblas_kernel

pin_openblas_kernel()  # before numpy, faiss or OpenCV load their OpenBLAS: one kernel for all (mapkit.core.blas)

__version__ = "0.1.0"
