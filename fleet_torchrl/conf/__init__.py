"""The packaged Hydra configs (YAML); a package so that Hydra finds them as
``pkg://fleet_torchrl.conf`` when a command runs from its console script."""
