"""Servo bus throughput: sync write / sync read of 16 simulated XL330s vs the vendor SDK and the wire-time bound."""

from __future__ import annotations

import time

import numpy as np

BAUD = 1_000_000
N_SERVOS = 16


def _wait_goals(sim, expected: int, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with sim.lock:
            got = sum(s.goals_received for s in sim.servos.values())
        if got >= expected:
            return
        time.sleep(0.0005)
    raise RuntimeError(f"simulator received {got} of {expected} goal positions")


def _goals(sim) -> int:
    with sim.lock:
        return sum(s.goals_received for s in sim.servos.values())


def run(quick: bool, log) -> dict:
    from dynamixel_sdk import GroupSyncRead, GroupSyncWrite, PortHandler

    from livebridge.devices.registry import open_bus
    from livebridge.drivers import dynamixel_protocol as dxl
    from livebridge.servo.bus import ServoSetup
    from livebridge.servo.output import ServoOutput
    from livebridge.servo.rig import demo_rig

    frames = 300 if quick else 3000
    reads = 100 if quick else 1000
    ids = list(range(1, N_SERVOS + 1))
    url = f"simdynamixel://?ids=1-{N_SERVOS}&model=XL330-M288&baud={BAUD}&delay=0"
    bus = open_bus(url)
    sim = bus.companion
    result: dict = {"servos": N_SERVOS, "baud": BAUD, "model": "XL330-M288", "frames": frames, "reads": reads,
                    "transport": "pseudo-terminal (no wire time)"}
    try:
        bus.configure([ServoSetup(i, 1024, 3072, 2048, "XL330-M288", f"s{i}") for i in ids], 0.02)
        bus.activate()
        rng = np.random.default_rng(0)
        goals = rng.integers(1100, 3000, size=(frames, N_SERVOS))

        # --- sync write: ours (DynamixelBus.write) vs the SDK's GroupSyncWrite on the same bus --------------
        base = _goals(sim)
        tx0 = bus.stats["tx_bytes"]
        t0 = time.perf_counter()
        for row in goals:
            bus.write(dict(zip(ids, row.tolist())))
        _wait_goals(sim, base + frames * N_SERVOS)
        ours_write = frames / (time.perf_counter() - t0)
        bytes_per_frame = (bus.stats["tx_bytes"] - tx0) / frames
        exact = len(dxl.sync_write(116, 4, {i: dxl.u32(2048) for i in ids}))
        assert bytes_per_frame == exact, (bytes_per_frame, exact)

        # the peer: the vendor SDK as shipped, on its own PortHandler of the same pseudo-terminal (our port
        # waits for replies in select; the SDK's spins on non-blocking reads)
        sdk_port = PortHandler(bus.port.getPortName())
        if not (sdk_port.openPort() and sdk_port.setBaudRate(BAUD)):
            raise RuntimeError(f"the SDK could not open {bus.port.getPortName()}")
        writer = GroupSyncWrite(sdk_port, bus.ph, 116, 4)
        for i in ids:
            writer.addParam(i, list(dxl.u32(2048)))
        base = _goals(sim)
        t0 = time.perf_counter()
        for row in goals:
            for i, g in zip(ids, row.tolist()):
                writer.changeParam(i, list(dxl.u32(g)))
            writer.txPacket()
        _wait_goals(sim, base + frames * N_SERVOS)
        sdk_write = frames / (time.perf_counter() - t0)

        # --- sync read of present position: ours (fast + plain) vs SDK GroupSyncRead ---------------------------
        t0 = time.perf_counter()
        ok = sum(len(bus.sync_read(132, 4, ids)) == N_SERVOS for _ in range(reads))
        ours_read = reads / (time.perf_counter() - t0)
        fast = bus._use_fast
        bus._use_fast = False
        t0 = time.perf_counter()
        ok_plain = sum(len(bus.sync_read(132, 4, ids)) == N_SERVOS for _ in range(reads))
        ours_read_plain = reads / (time.perf_counter() - t0)
        bus._use_fast = fast

        reader = GroupSyncRead(sdk_port, bus.ph, 132, 4)
        for i in ids:
            reader.addParam(i)
        t0 = time.perf_counter()
        sdk_ok = sum(reader.txRxPacket() == 0 for _ in range(reads))
        sdk_read = reads / (time.perf_counter() - t0)
        t0 = time.perf_counter()
        sdk_fast_ok = sum(reader.fastSyncRead() == 0 for _ in range(reads))
        sdk_read_fast = reads / (time.perf_counter() - t0)
        sdk_port.closePort()
        # positions read back agree with the simulator's truth
        truth = {i: sim.servo(i).get("present_position") for i in ids}
        got = {i: dxl.to_int(d, signed=True) for i, (d, _) in bus.sync_read(132, 4, ids).items()}
        read_error = max(abs(got[i] - truth[i]) for i in ids)
    finally:
        bus.close()

    # --- the whole output path: mapping + safety + sync write + poll, per frame ---------------------------------
    rig = demo_rig(url)
    out = ServoOutput(rig, [s.name for s in rig.servos], poll_every=5)
    try:
        out.configure()
        out.activate(t=0.0)
        x = np.clip(np.random.default_rng(1).random((frames // 2, N_SERVOS)), 0, 1)
        t0 = time.perf_counter()
        for k, row in enumerate(x):
            out.send(row, t=k * 0.02)
        output_rate = len(x) / (time.perf_counter() - t0)
    finally:
        out.state = None
        out.close(ease=False)

    read_tx = len(dxl.sync_read(132, 4, ids))
    read_rx_plain = N_SERVOS * len(dxl.encode_status(1, 0, b"\0" * 4))
    read_rx_fast = len(dxl.encode_fast_sync_status([(0, i, b"\0" * 4) for i in ids]))
    byte_rate = BAUD / 10.0  # 8N1: 10 bits per byte
    write_bound = byte_rate / bytes_per_frame
    read_bound = byte_rate / (read_tx + (read_rx_fast if fast else read_rx_plain))
    read_bound_plain = byte_rate / (read_tx + read_rx_plain)
    result.update({
        "sync_write_per_s": round(ours_write, 1),
        "sync_write_per_s_sdk": round(sdk_write, 1),
        "sync_write_vs_sdk": round(ours_write / sdk_write, 3),
        "bytes_per_frame": bytes_per_frame,
        "wire_bound_write_per_s": round(write_bound, 1),
        "sync_write_ratio_to_wire": round(ours_write / write_bound, 3),
        "sync_read_per_s": round(ours_read, 1),
        "sync_read_fast": bool(fast),
        "sync_read_complete": ok / reads,
        "sync_read_plain_per_s": round(ours_read_plain, 1),
        "sync_read_plain_complete": ok_plain / reads,
        "sync_read_per_s_sdk": round(sdk_read, 1),
        "sync_read_fast_per_s_sdk": round(sdk_read_fast, 1),
        "sdk_read_success": (sdk_ok + sdk_fast_ok) / (2 * reads),
        "sync_read_vs_sdk": round(ours_read / (sdk_read_fast if fast else sdk_read), 3),
        "bytes_per_read": read_tx + (read_rx_fast if fast else read_rx_plain),
        "wire_bound_read_per_s": round(read_bound, 1),
        "sync_read_ratio_to_wire": round(ours_read / read_bound, 3),
        "sync_read_plain_ratio_to_wire": round(ours_read_plain / read_bound_plain, 3),
        "read_position_error_ticks": int(read_error),
        "output_frames_per_s": round(output_rate, 1),
    })
    # The driver must not be the bottleneck of a real 1 Mbaud bus, nor much slower than the bare SDK.
    result["pass"] = bool(result["sync_write_ratio_to_wire"] >= 1.0 and result["sync_write_vs_sdk"] >= 0.5
                          and result["sync_read_complete"] == 1.0 and read_error == 0)
    log(f"sync write {ours_write:.0f}/s (SDK {sdk_write:.0f}/s), wire bound {write_bound:.0f}/s; "
        f"sync read {ours_read:.0f}/s, wire bound {read_bound:.0f}/s")
    return result
