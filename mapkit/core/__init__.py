"""The base every stage stands on: types, errors, geometry, frames, geodesy, configs, atomic run
I/O, bundles, the executor and the Workspace that owns the folder layout. Imports nothing else of
mapkit."""
