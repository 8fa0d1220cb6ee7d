"""One error family for the whole package.

The CLI turns every :class:`CampaignError` into one line on stderr and a non-zero exit.
"""


class CampaignError(Exception):
    """Root of every error `campaign` raises on purpose."""


class ConfigError(CampaignError):
    """A configuration, robot or scene file is malformed or inconsistent."""


class DataError(CampaignError):
    """Measured data (CSV, SQLite) is malformed, inconsistent or out of range."""


class NotFittedError(CampaignError):
    """A model was used before ``fit`` was called."""


class IdentificationError(CampaignError):
    """The identification did not converge or the problem is degenerate."""


class ProtocolError(CampaignError):
    """A peer sent a message that does not follow the wire protocol."""


class PeerError(CampaignError):
    """A peer could not be reached, or refused, or reported a fault."""


class TrackerTimeout(PeerError):
    """The laser tracker did not answer in time."""


class RobotFault(PeerError):
    """The robot controller reported a fault; the campaign must stop."""


class StorageError(CampaignError):
    """A file or the measurement log could not be written (full disk, locked database, ...);
    nothing stored before is lost."""


class RunBusy(CampaignError):
    """Another process drives this run (its lock is held)."""


class RunHoldsMeasurements(CampaignError):
    """The command would replace or delete measurements; it refuses."""


class PlanError(CampaignError):
    """The configuration is valid but no plan can be made from it (e.g. no suitable pose)."""


class AuthError(ProtocolError):
    """A frame failed authentication (no, wrong or replayed shared secret), or a peer that
    should authenticate its frames did not; nothing it asked is done."""


class Implausible(CampaignError):
    """With ``--strict``: the data or the result fail a plausibility check; nothing was written.
    ``warnings``: the plausibility warnings (campaign.measure.plausibility.Finding)."""

    def __init__(self, message: str, warnings=()):
        super().__init__(message)
        self.warnings = tuple(warnings)


class PluginError(CampaignError):
    """A user's effect (``file.py:Class``) or an installed plug-in failed in one of its hooks:
    it raised, or returned the wrong shape or values that are not finite."""
