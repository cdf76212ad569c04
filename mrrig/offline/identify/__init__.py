"""`mrrig identify`: the modified Bouc-Wen model (eqs 30-36) fitted to a measured damper, a
twin that `firmware_sim` runs (`[plant] file = ...`). `fit` is the pure numerics, `identify`
the files around it (data in, report and plant file out)."""
