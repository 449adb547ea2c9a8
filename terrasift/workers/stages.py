"""Imports every stage module so each registers itself with the registry."""

# Stage modules are imported for their registration side effect.
