"""Primary configs of the file tools that take none of the model's groups (``compare``), kept
apart from ``conf/``: Hydra's tab completion offers every group of an app's config folder, so
a tool whose folder held ``agent/`` and ``site/`` would offer ``agent=`` and ``site=``, which it
rejects. A package so that Hydra finds them as ``pkg://fleet_torchrl.tool_conf`` when a
command runs from its console script."""
