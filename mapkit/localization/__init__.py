"""The Monte Carlo visual localizer: the particle filter and the localizer that runs it on a VLAD
bundle."""
