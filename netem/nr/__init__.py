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

A direction with a radio leaves data only in its TDD windows (uplink slots and the special
slot's uplink symbols, or the downlink ones), each window carrying at most its transport block
(TS 38.214 §5.1.3.2 from PRBs, MCS and layers); a packet leaves at the end of the window that
carried its last byte. Every relay's slot grid starts at 0 on the host's monotonic clock, so the
links of a host share one grid.

How the uplink gets its windows (`access`):
- `sr` (default, as OAI and srsRAN run): data that no buffer status report has announced
  triggers a scheduling request in the next SR occasion (every `sr_period` slots, in slot
  `sr_offset`), unless a PUSCH goes first. The SR brings a small first grant (`sr_grant` bytes)
  `grant_slots` + `k2` slots after it. Every PUSCH carries a buffer status report of what had
  arrived when it started, and the gNB grants what the reports announced the same delay after
  it decoded them (TS 38.321 §5.4.4, §5.4.5). So a 92-byte probe on `oai-tdd-30k` takes two
  rounds of one TDD period each: the SR, then its report.
- `configured`: a configured grant every `cg_period` slots in slot `cg_offset`, no request
  (TS 38.321 §5.8.2): the delay is uniform over the grant's period.
- `ideal`: a gNB that sees the UE's buffer at once, any window `k2` slots after the data
  arrives (a bound; also how the downlink, whose data the gNB holds, is scheduled).

HARQ: a block fails with probability `bler` and is resent in the first window that starts
`harq_slots` after it with the block's bytes free (taken from that window's new data), at most
`max_retx` times. Then RLC: in `am` (default, as OAI and srsRAN run their default bearers) the
block's packets are back in the sender's buffer `rlc_status` (20 ms) later and resent, so
nothing is lost while the link holds; a packet is given up after `rlc_max_retx` resends
(maxRetxThreshold, TS 38.322 §5.3.2; default 32 as OAI configures its DRBs) and counted as an
`rlc` drop: without that bound a packet out of coverage (BLER near 1) came back for ever and a
replay whose route left coverage never finished. In `um` they are lost (and a buffer status
report the block carried, which the UE then asks for again). Packets leave in arrival order, as
PDCP delivers them (a late one holds back those behind it); `in_order: false` lets each leave
when decoded.

Named radios (each field's source is in `radio`, which defines them): those calibrated on a
published measurement, `srsran-urllc`, `oai-usrp-edaf`, `sa-midband-ericsson` and
`public-n78-cicv5g` (`testbed fidelity` judges each against its source, `testbed.fidelity`);
and `oai-tdd-30k`, `srsran-lowlat`, `commercial-midband` (a 100 MHz n78-like cell, DDDDDDDSUU,
an SR every 10 ms, RLC status 20 ms, the core 3 ms from the gNB), which follow a configuration
file or common practice but no measurement: each says in `radio` what it assumes.

Shared cells: the air links of one gNB with a radio share one relay process and its slots; in
each occasion retransmissions go first, then the cell's `scheduler` (`rr`, `pf`) splits the
rest of the PRBs among the UEs that have data, each sending its share at its own MCS.
tests/test_relay_root.py floods one cell's uplink from two UEs under rr and under pf and
requires each to carry 40-60% of it and both together the cell's goodput within 5%. `testbed
run scenarios/multi_vehicle_nr.yaml` (four vehicles, 40 s, 2-core host): every air link's
self-test within tolerance, 472-521 answers per vehicle, a mean request latency of 120-138 ms
in every split against 45-88 ms for one vehicle on nr_cell; with 13 ROS nodes on 2 cores most
of that is the host, not the cell (each UE's idle radio delay stayed ~13 ms up, ~2 ms down).
"""
