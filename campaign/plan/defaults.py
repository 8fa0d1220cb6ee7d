"""The short campaign's sizes, apart from the selection's numerics so that `campaign plan --help`
names them without importing numpy or scipy (campaign.plan.selection re-exports them)."""

#: poses of the default `campaign plan` (the short campaign for the physical model), with its
#: validation poses and repeats: benchmarks/results/select.json on the default cell (hidden
#: geometry + elastic ground, 10 µm noise): 120 D-optimal poses are 1.027× the full campaign's
#: held-out error (60: 1.062×, 250: 1.022×) in 0.76 h with validation and repeats instead of 38 h
#: (1.98 days for all 9,829 suitable poses); the model against the truth 2.5 µm mean position
DEFAULT_SELECT = 120
#: with a selection: this many chosen poses are measured REPEAT_TIMES times back to back (each
#: repeat after one other tour pose, campaign.plan.selection.CampaignChoice.with_repeats) for the
#: noise floor (campaign.measure.floor): 3 × 4 give 9 successive differences, 27 per coordinate,
#: a floor known to ±17 % (1 σ; 3 × 3 gave ±20 %), for 3 more measurements than 3 × 3 (the
#: default short campaign stays under half of `--all` on the coarse test grid)
REPEAT_POSES = 3
REPEAT_TIMES = 4
