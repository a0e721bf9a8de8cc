"""The NR radio: what a link's air interface is (below the stages) and how a UE and a cell
move packets through it (above them).

Below `netem.stages` (plain data and pure functions that `netem.profile` carries):
- `phy`: numerology, TDD patterns, carriers, occasions, transport block sizes;
- `oracle`: the closed-form idle delay of a direction; `radio`: a link's `Radio`, its `Grid`s
  and the named radios of real gNBs;
- `rrc`: the RRC state machine and its timers; `channel`: path loss, shadowing and fading to
  SINR, MCS and BLER; `handover`: A3 decisions from RSRP measurements.

Above `netem.stages` (stages, and what shares them):
- `ue`: one UE's direction of the air link (`Slots`: MAC grants, HARQ, RLC, PDCP);
- `cell`: the UEs of one gNB sharing its occasions, by a scheduler `policy` (rr, pf);
- `rrc_stage`: the RRC states as a stage; `handover_gap`: a handover's interruption.
"""
