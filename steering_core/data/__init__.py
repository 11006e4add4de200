"""Phase 1, data: LIBERO demos -> filtered files -> LeRobot dataset -> contrast manifests -> concept maps.

Modules in pipeline order: `libero` (hdf5 schema), `filtering`, `convert`, `dataset` (reading datasets
without frames), `contrast` (manifests), `concept_map`.
"""
