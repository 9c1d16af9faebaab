"""The defaults of a run file's application slots (`reachwatch.diagrams.schemas`):
a field holding an environment or a random family takes the application's default for
its role."""

import dataclasses as dc

from reachwatch.diagrams.schemas import ApplicationEnvironment, ApplicationRandomEnvironments
from reachwatch.reach.application import Application, load_application

#: The application a run file that names none (or names "") studies: the taxi
#: (`reachwatch.taxi.application.TAXI_APPLICATION`; named here, not imported, so that the
#: generic pipeline imports no taxi code).
DEFAULT_APPLICATION = "reachwatch.taxi.application:TaxiApplication"


def is_default_application(application: Application) -> bool:
    """Whether ``application`` is the one `DEFAULT_APPLICATION` names (however it was
    named)."""
    return type(application) is type(load_application(DEFAULT_APPLICATION))


@dc.dataclass(frozen=True)
class SlotDefaults:
    """``defaults(slot, role)`` of `typed_schema` for ``application`` (None:
    `DEFAULT_APPLICATION`, loaded when a default is first made): a factory of the
    application's environment (`Application.default_environment`) or random family
    (`Application.default_random_environments`) for ``role``."""
    application: Application = None

    def __call__(self, slot, role):
        def make():
            application = self.application or load_application(DEFAULT_APPLICATION)
            environment, family = application.run_file_types()
            if slot is ApplicationEnvironment:
                made, kind, how = (application.default_environment(role), environment,
                                   "default_environment")
            elif slot is ApplicationRandomEnvironments:
                made, kind, how = (application.default_random_environments(role), family,
                                   "default_random_environments")
            else:
                raise TypeError(f"not an application slot: {slot!r}")
            if type(made) is not kind:          # e.g. a subclass that changed the type only
                raise ValueError(f"application {application.name!r}: {how}({role!r}) gave a "
                                 f"{type(made).__name__}, not its {kind.__name__}")
            return made
        return make


def application_default(slot, role: str):
    """The default factory of a slot field in a schema built in code: the default
    application's."""
    return SlotDefaults()(slot, role)
