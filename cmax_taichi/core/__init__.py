"""Core objects: events and camera, backend, registries, pooled workspaces."""
