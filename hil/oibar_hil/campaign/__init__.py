"""Monte Carlo dispersion campaigns on the HIL rig (issue 62, docs/campaign.md).

A campaign flies N missions, each a rig scenario made from one draw of a seeded dispersion
model (hil/campaigns/*.toml), and states how often the system docks (or, with a fault drawn,
ends the way the fault matrix expects) with a Clopper-Pearson bound.

    python -m oibar_hil.campaign run --config hil/campaigns/default.toml --missions 1000
    python -m oibar_hil.campaign report build/campaigns/default
    python -m oibar_hil.campaign replay build/campaigns/default 17

Pieces:
- ``dispersion``: the TOML model, its validation and the draws; mission i of campaign seed s is
  drawn from ``SeedSequence(s, spawn_key=(i, crc32(stream)))``, so it never depends on the
  other missions, on the order they run in or on the machine;
- ``mission``: a draw -> a rig ``Scenario`` (and its navigation) -> ``Rig.run()`` -> one row;
- ``store``: the campaign folder, one Parquet part per finished mission (resume = skip them);
- ``execute``: Ray tasks (retried when a worker is lost) or one process, the live progress;
- ``stats``, ``report``: Clopper-Pearson, failure drivers, figures, the worst missions.
"""
