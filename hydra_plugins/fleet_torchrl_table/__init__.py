"""fleet_torchrl's Hydra sweeper for ``make table`` (Hydra loads sweepers only from its
``hydra_plugins`` package); the work is in :mod:`fleet_torchrl.experiments.launch`."""
