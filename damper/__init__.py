"""The damper's physics, shared by the simulated rig (`firmware_sim`) and the rig service
(`mrrig`): the modified Bouc-Wen plant (paper eqs 30-36) and the excitation signals.

Pure numerics: nothing here knows of CAN, Zenoh, Rerun or either package that imports it.
"""
