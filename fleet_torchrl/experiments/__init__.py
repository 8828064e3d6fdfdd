"""The experiments of MODEL §5 as library functions (the commands call them): the main table,
policy maps, generalisation sweeps, the grid-search summary, the objective check, the
report and the throughput benchmark."""
