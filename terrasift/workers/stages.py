"""Imports every stage module so each registers itself with the registry."""

# Stage modules are imported for their registration side effect.
import terrasift.workers.categories  # noqa: F401
import terrasift.workers.features  # noqa: F401
import terrasift.workers.ground.landforms  # noqa: F401
import terrasift.workers.ground.lowpoints  # noqa: F401
import terrasift.workers.ground.lowveg  # noqa: F401
import terrasift.workers.ground.nist  # noqa: F401
import terrasift.workers.ground.ptd  # noqa: F401
import terrasift.workers.ground.rotation  # noqa: F401
import terrasift.workers.mixed  # noqa: F401
import terrasift.workers.objects  # noqa: F401
import terrasift.workers.steps  # noqa: F401
import terrasift.workers.terrain  # noqa: F401
import terrasift.workers.vegetation  # noqa: F401
