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
