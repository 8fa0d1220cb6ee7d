"""`campaign diagnose`: where the model fails and which physical effect is missing."""

__all__ = ["Diagnosis", "diagnose"]


def __getattr__(name):
    # lazy (PEP 562): `campaign --help` imports campaign.diagnose.commands, and that must not
    # import the engine's numpy, scipy and effects (campaign.cli: the parser stays cheap)
    if name in __all__:
        from campaign.diagnose import engine

        return getattr(engine, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
