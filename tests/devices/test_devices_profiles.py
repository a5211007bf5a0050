"""Each profile method against its simulator over the virtual RS-485 bus: one
`pyrtu.Master` on drop 0 and the six simulated drives on the other drops of one
shared bus (RTU), plus the ASCII variants.  The bus runs in real time; the drives'
model runs on one `ManualClock`, which `_wait` moves, so a ramp or a holding time ends
when the test says, however loaded the machine (CI lost a 0.3 s sleep to load)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import pytest

from pyrtu.devices import (
    ACT,
    ACU,
    CFW100,
    CFW320,
    CFW701,
    CV100,
    ACTSimulator,
    ACUSimulator,
    CFW100Simulator,
    CFW320Simulator,
    CFW701Simulator,
    CV100Simulator,
    DriveState,
    ErrorAction,
    InterfaceStatus,
    ManualClock,
    WegSimulator,
    bonfiglioli,
    cv100,
)
from pyrtu.drivers.master import Master
from pyrtu.pdu.errors import ExceptionResponseError
from pyrtu.vbus import VirtualBus

BAUD = 57600
ADDRESSES = {"cfw100": 1, "cfw320": 2, "cfw701": 3, "cv100": 5, "act": 6, "acu": 7}


@dataclass
class Bus:
    master: Master
    cfw100: CFW100Simulator
    cfw320: CFW320Simulator
    cfw701: CFW701Simulator
    cv100: CV100Simulator
    act: ACTSimulator
    acu: ACUSimulator


CLOCK = ManualClock(1000.0)


@pytest.fixture(scope="module")
def bus() -> Iterator[Bus]:
    sims = {
        "cfw100": CFW100Simulator(state="stopped", clock=CLOCK),
        "cfw320": CFW320Simulator(clock=CLOCK),
        "cfw701": CFW701Simulator(clock=CLOCK),
        "cv100": CV100Simulator(state="stopped", clock=CLOCK),
        "act": ACTSimulator(fault_lock_time=0.2, clock=CLOCK),
        "acu": ACUSimulator(fault_lock_time=0.2, clock=CLOCK),
    }
    with VirtualBus(1 + len(sims), baudrate=BAUD, parity="N") as vbus:
        for drop, (name, sim) in enumerate(sims.items(), start=1):
            sim.serve(vbus.paths[drop], ADDRESSES[name], baudrate=BAUD, parity="N")
        master = Master(vbus.paths[0], BAUD, parity="N", timeout=0.5)
        try:
            yield Bus(master, **sims)  # type: ignore[arg-type]
        finally:
            master.close()
            for sim in sims.values():
                sim.close()


def _wait(seconds: float) -> None:
    """The drives' time moves on by ``seconds`` (their model catches up on the next telegram)."""
    CLOCK.advance(seconds)


# -- WEG ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "cls"), [("cfw100", CFW100), ("cfw320", CFW320), ("cfw701", CFW701)]
)
def test_weg_profile_start_speed_stop(bus: Bus, name: str, cls: type[CFW701]) -> None:
    sim: WegSimulator = getattr(bus, name)
    drive = cls(bus.master, ADDRESSES[name])
    assert drive.identify() == {"vendor": "WEG", "product_code": name.upper(), "revision": "V1.00"}
    assert drive.rated_hz() == 60.0 and drive.read(308) == ADDRESSES[name]
    drive.write_many(100, [2, 2])  # 0.2 s from 0 to 66 Hz: 30 Hz after 0.091 s
    drive.set_speed_hz(30)
    assert drive.reference_hz() == pytest.approx(30.0)
    drive.start()
    ramp = 30 / 66 * 0.2
    _wait(ramp + 0.05)
    assert drive.speed_hz() == pytest.approx(30.0, abs=0.01)  # 30 Hz after the ramp time
    st = drive.status()
    assert st.running and st.forward and st.remote and st.enabled and not st.fault
    assert drive.control().run and drive.motor_current_a() == pytest.approx(1.5, abs=0.1)
    drive.set_speed_hz(-30)
    _wait(2 * ramp + 0.05)
    assert drive.speed_hz() == pytest.approx(-30.0, abs=0.01) and not drive.status().forward
    drive.set_direction(False)  # bit 2 = 0: against the (negative) reference: forward
    _wait(2 * ramp + 0.05)
    assert drive.frequency_hz() == pytest.approx(30.0, abs=0.01)
    drive.stop()
    _wait(ramp + 0.05)
    assert drive.speed_hz() == 0.0 and not drive.status().running
    assert sim.speed_hz() == 0.0


def test_weg_profile_commands(bus: Bus) -> None:
    sim = bus.cfw701
    drive = CFW701(bus.master, ADDRESSES["cfw701"], rated_hz=60)
    drive.write_many(100, [1, 1])
    drive.set_speed_hz(20)  # JOG runs in the direction of the reference and bit 2
    drive.jog()
    _wait(0.1)
    assert drive.status().jog and drive.speed_hz() == pytest.approx(5.0, abs=0.01)
    drive.jog(False)
    drive.second_ramp(True)
    assert drive.status().second_ramp
    drive.second_ramp(False)
    drive.start()
    _wait(0.1)
    drive.disable()
    st = drive.status()
    assert not st.enabled and not st.running and drive.speed_hz() == 0.0
    drive.enable()
    drive.set_remote(False)
    assert not drive.status().remote
    drive.set_remote(True)
    sim.inject_fault(33)
    assert drive.status().fault and drive.fault() == 33
    drive.reset_fault()
    assert not drive.status().fault and drive.control().fault_reset is False
    drive.set_digital_outputs(0b10101)
    assert sim.get(695) == 0b10101
    drive.set_analog_output(1, 0.5)
    drive.set_analog_output(2, -1.0)
    assert sim.get(696) == 16384 and sim.get(697) == 0x8001
    with pytest.raises(ValueError):
        drive.set_digital_outputs(0x20)
    with pytest.raises(ValueError, match="no digital output word"):
        CFW100(bus.master, 1).set_digital_outputs(1)
    with pytest.raises(ValueError, match="no analog output"):
        CFW100(bus.master, 1).set_analog_output(1, 0.5)
    drive.fast_stop()
    assert drive.control().fast_stop
    drive.stop()
    with pytest.raises(ExceptionResponseError) as exc:
        drive.write(2900, 0)
    assert exc.value.code == 2
    with pytest.raises(ExceptionResponseError) as exc:
        drive.write(680, 0)
    assert exc.value.code == 3


def test_weg_profile_watchdog(bus: Bus) -> None:
    drive = CFW320(bus.master, ADDRESSES["cfw320"], rated_hz=60, reference_register=685)
    drive.write_many(100, [1, 1])
    drive.set_speed_hz(10)
    drive.set_watchdog(0.2, ErrorAction.RAMP_STOP)  # CFG parameters: with the motor stopped
    assert bus.master.read_holding_registers(2, 314, 1) == [2]
    drive.start()
    _wait(0.3)  # no telegram to this drive
    assert drive.interface_status() is InterfaceStatus.WATCHDOG_ERROR  # seen by the first
    st = drive.status()  # the second one: the alarm is gone, the ramp stop stays
    assert not st.alarm and not drive.control().run and drive.alarm() == 0
    assert drive.interface_status() is InterfaceStatus.ACTIVE
    _wait(0.15)
    assert drive.speed_hz() == 0.0
    drive.set_watchdog(0)
    drive.stop()


# -- CV100 ------------------------------------------------------------------------------------


def test_cv100_profile(bus: Bus) -> None:
    sim = bus.cv100
    drive = CV100(bus.master, ADDRESSES["cv100"])
    assert drive.identify() == {"slave_model": 100, "vfd_model": 1, "software_version": 100}
    drive.set_accel_time(0.2)
    drive.set_decel_time(0.2)
    assert drive.accel_time() == 0.2 and drive.read("A0.07") == 2
    drive.set_frequency_hz(20)
    drive.run_forward()
    assert drive.read(cv100.CONTROL_WORD_1) == 0x01C7  # bit 8: main reference
    _wait(0.2)
    assert drive.frequency_hz() == 20.0 and drive.reference_hz() == 20.0
    st = drive.status()
    assert st.word1.running and st.word1.at_reference and "constant_speed" in st.word3
    assert drive.output_current_a() == pytest.approx(12.0)
    drive.run_reverse()
    _wait(0.3)
    assert sim.frequency_hz() == -20.0 and drive.status().word1.reverse
    drive.stop()
    _wait(0.2)
    assert drive.frequency_hz() == 0.0 and not drive.status().word1.running
    drive.jog_forward()
    _wait(0.1)
    assert drive.frequency_hz() == 5.0 and "jog" in drive.status().word2
    drive.stop_jog()
    drive.jog_reverse()
    drive.coast_stop()  # jog bits off, coast
    drive.external_fault_stop()
    assert drive.status().word1.fault and drive.faults()[2] == 15
    drive.reset_fault()
    assert not drive.status().word1.fault
    drive.control_word_2(cv100.ControlWord2(operation_disable=True))
    drive.control_word_2(cv100.ControlWord2())
    drive.write("A0.05", 7, save=True)
    drive.write_many("A0.03", [1, 2], save=True)
    drive.write("A0.08", 9)
    sim.power_cycle()
    assert drive.read_many("A0.03", 6) == [1, 2, 7, 60, 60, 0]  # FC 06 writes are lost
    assert drive.manage(cv100.Manage.FACTORY_VALUE, cv100.register("A0.07")) == 60
    drive.enter_password(0)


def test_cv100_profile_ascii() -> None:
    sim = CV100Simulator()
    with VirtualBus(2, baudrate=BAUD, parity="N") as vbus:
        sim.serve(vbus.paths[1], 5, baudrate=BAUD, parity="N", mode="ascii")  # switches it
        assert sim.mode == "ascii"
        with Master(vbus.paths[0], BAUD, parity="N", mode="ascii", timeout=0.5) as master:
            drive = CV100(master, 5)
            assert drive.reference_hz() == 50.0 and drive.output_current_a() == 30.0
            assert drive.decel_time() == 6.0
            drive.write("A2.01", 3)
            drive.write("A2.02", 4, save=True)
            assert drive.read_many("A2.01", 2) == [3, 4]
            assert sim.slave is not None and sim.slave.response_delay == 0.001
        sim.close()


# -- Bonfiglioli ----------------------------------------------------------------------------------


@pytest.mark.parametrize(("name", "cls"), [("act", ACT), ("acu", ACU)])
def test_vectron_profile_state_machine(bus: Bus, name: str, cls: type[ACT]) -> None:
    sim: ACTSimulator | ACUSimulator = getattr(bus, name)
    drive = cls(bus.master, ADDRESSES[name])
    assert drive.state() is DriveState.STARTING_LOCKOUT
    drive.write(bonfiglioli.P_ACCELERATION, 200.0)  # Hz/s
    drive.write(bonfiglioli.P_DECELERATION, 200.0)
    drive.set_frequency_hz(30)
    drive.shutdown()
    assert drive.state() is DriveState.READY
    drive.switch_on()
    assert drive.state() is DriveState.SWITCHED_ON
    drive.enable_operation()
    st = drive.status()
    assert st.state is DriveState.OPERATION_ENABLED and st.remote
    assert st.voltage is (name == "acu")
    _wait(0.25)
    assert drive.frequency_hz() == pytest.approx(30.0) and drive.status().reference_reached
    drive.write(bonfiglioli.P_EMERGENCY_CW, 300.0)  # Hz/s
    drive.write(638, 0.1)  # holding time
    drive.quick_stop()
    assert drive.state() is DriveState.QUICK_STOP
    _wait(0.19)  # 30 Hz at 300 Hz/s is 0.1 s, then the holding time of 0.1 s
    assert drive.state() is DriveState.QUICK_STOP
    _wait(0.02)
    assert drive.state() is DriveState.STARTING_LOCKOUT and drive.frequency_hz() == 0.0
    assert drive.start(30) is DriveState.OPERATION_ENABLED
    drive.disable_voltage()  # coasts at once
    assert drive.state() is DriveState.STARTING_LOCKOUT and drive.frequency_hz() == 0.0
    assert drive.start(30) is DriveState.OPERATION_ENABLED
    drive.write(bonfiglioli.P_STATE_TRANSITION_5, 0)  # coast
    drive.stop()
    assert drive.state() is DriveState.SWITCHED_ON
    sim.fault(0x0500)
    assert drive.state() is DriveState.FAULT and drive.current_error() == "F0500"
    with pytest.raises(RuntimeError):
        drive.start()
    _wait(0.25)
    drive.reset_fault()
    assert drive.state() is DriveState.STARTING_LOCKOUT and drive.current_error() == "F0000"
    drive.write(bonfiglioli.P_STATE_TRANSITION_5, 2)


def test_vectron_profile_parameters_and_diagnostics(bus: Bus) -> None:
    drive = ACT(bus.master, ADDRESSES["act"])
    assert drive.identify() == {
        "vendor": "Bonfiglioli Vectron",
        "model": "ACT",
        "protocol": "Modbus RTU",
        "address": "6",  # Modbus Address 1376: the address the simulator serves
    }
    assert drive.read(bonfiglioli.P_RATED_SPEED, 2) == 1390
    assert drive.read(bonfiglioli.P_FIXED_FREQUENCY_2) == 10.0
    drive.write(bonfiglioli.P_RATED_FREQUENCY, 10.0, 2)
    assert drive.read(bonfiglioli.P_RATED_FREQUENCY, 2) == 10.0
    with pytest.raises(ExceptionResponseError) as exc:
        drive.write(bonfiglioli.P_RATED_FREQUENCY, 9.0, 2)
    assert (
        exc.value.code == 4 and drive.error_register() is bonfiglioli.VabusError.INADMISSIBLE_VALUE
    )
    assert drive.error_register() is bonfiglioli.VabusError.NO_ERROR
    drive.write(bonfiglioli.P_RATED_POWER, 1.5, 4, ram=True)
    assert drive.read(bonfiglioli.P_RATED_POWER, 4) == 1.5
    with pytest.raises(ExceptionResponseError):
        drive.read_raw(1600, 2, size=4)
    drive.select_data_set(2)
    assert drive.active_data_set() == 2
    drive.select_data_set(0)
    drive.set_percentage(-12.5)
    assert drive.warnings() == []
    drive.clear_counters()
    assert drive.diagnostic_counter("slave_message_count") == 1
    counters = drive.diagnostic_counters()
    # read in sub-function order 0x0B..0x12: the slave message count (0x0E) is the 4th
    assert counters["slave_message_count"] == 1 + 4 and counters["slave_nak_count"] == 0


def test_vectron_profile_watchdog(bus: Bus) -> None:
    drive = ACU(bus.master, ADDRESSES["acu"])
    assert drive.start(5) is DriveState.OPERATION_ENABLED
    drive.set_watchdog(1)
    _wait(1.1)
    assert drive.state() is DriveState.FAULT and drive.current_error() == "F2010"
    drive.set_watchdog(0)
    _wait(0.2)
    drive.reset_fault()
    assert drive.state() is DriveState.STARTING_LOCKOUT


def test_vectron_profile_ascii() -> None:
    sim = ACTSimulator(mode="ascii")
    with VirtualBus(2, baudrate=BAUD, parity="N") as vbus:
        sim.serve(vbus.paths[1], 1, baudrate=BAUD, parity="N")
        with Master(vbus.paths[0], BAUD, parity="N", mode="ascii", timeout=0.5) as master:
            drive = ACT(master, 1)
            assert drive.read(bonfiglioli.P_FIXED_FREQUENCY_2) == 10.0
            assert drive.start(10) is DriveState.OPERATION_ENABLED
            with pytest.raises(ExceptionResponseError) as exc:
                drive.write(bonfiglioli.P_RATED_SPEED, 1400, 1)  # rated data: not while running
            assert (
                exc.value.code == 4
                and drive.error_register() is bonfiglioli.VabusError.NOT_WHILE_RUNNING
            )
            assert drive.read_raw(bonfiglioli.P_RATED_SPEED, 1) == 1390
        sim.close()
