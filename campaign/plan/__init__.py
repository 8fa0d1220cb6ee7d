"""`campaign plan`: candidates -> suitable poses -> the most informative -> an ordered, collision-free tour
(campaign.plan.pipeline), and the ISO 9283 test plan beside it (campaign.iso9283)."""
