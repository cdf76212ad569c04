"""The offline work, in no process of the rig: data sets, training (torch), characterization
and validation runs, evaluation, review of recordings, simulation and the benchmarks."""
