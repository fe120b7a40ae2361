"""Auditor's own ur-rtde fake (no MuJoCo): kinematic arms, scriptable faults, every call recorded."""

from __future__ import annotations

import datetime

import numpy as np

from harvest_qp.robot.description import HOME_Q


class FakeCell:
    def __init__(self, hosts=("10.9.0.1", "10.9.0.2"), q0=None, dt=0.002):
        self.hosts = {hosts[0]: 0, hosts[1]: 1}
        self.dt = dt
        self.t = 0.0
        self.q = np.array(HOME_Q if q0 is None else q0, dtype=float)
        self.qd = np.zeros(12)
        self.wrench = np.zeros(6)  # getActualTCPForce of the grasping arm, as returned
        self.safety = [1, 1]
        self.status = [3, 3]
        self.connected = [False, False]
        self.frozen = [False, False]
        self.calls = []
        self.stamp = [100.0, 200.0]
        self.fail_connect = {}  # host -> exception instance raised by the constructor
        self.raise_on = {}  # (arm, method) -> exception instance
        self.return_on = {}  # (arm, method) -> value returned instead
        cell = self

        class _Base:
            def __init__(self, hostname, frequency=-1.0, *rest):
                if hostname in cell.fail_connect:
                    raise cell.fail_connect[hostname]
                if hostname not in cell.hosts:
                    raise RuntimeError(f"Could not connect to: {hostname}")
                self.host, self.arm = hostname, cell.hosts[hostname]
                cell.connected[self.arm] = True
                cell.calls.append((hostname, self.kind, "__init__", ()))

            def __getattr__(self, name):
                raise AttributeError(name)

            def _rec(self, name, args):
                cell.calls.append((self.host, self.kind, name, args))
                exc = cell.raise_on.get((self.arm, name))
                if exc is not None:
                    raise exc
                return cell.return_on.get((self.arm, name), _NO)

        class Control(_Base):
            kind = "control"

            def speedJ(self, qd, acceleration=0.5, time=0.0):
                r = self._rec("speedJ", (list(qd), acceleration, time))
                if r is not _NO:
                    return r
                cell.qd[6 * self.arm:6 * self.arm + 6] = qd
                return True

            def speedStop(self, a=10.0):
                r = self._rec("speedStop", (a,))
                cell.qd[6 * self.arm:6 * self.arm + 6] = 0.0
                return True if r is _NO else r

            def stopScript(self):
                self._rec("stopScript", ())

            def disconnect(self):
                self._rec("disconnect", ())

            def initPeriod(self):
                self._rec("initPeriod", ())
                return datetime.timedelta(seconds=cell.t)

            def waitPeriod(self, t0):
                self._rec("waitPeriod", (t0,))
                cell.tick()

            def zeroFtSensor(self):
                self._rec("zeroFtSensor", ())
                return True

            def setWatchdog(self, min_frequency=10.0):
                self._rec("setWatchdog", (min_frequency,))
                return True

            def kickWatchdog(self):
                self._rec("kickWatchdog", ())
                return True

        class Receive(_Base):
            kind = "receive"

            def getActualQ(self):
                r = self._rec("getActualQ", ())
                return list(cell.q[6 * self.arm:6 * self.arm + 6]) if r is _NO else r

            def getActualQd(self):
                r = self._rec("getActualQd", ())
                return list(cell.qd[6 * self.arm:6 * self.arm + 6]) if r is _NO else r

            def getActualTCPForce(self):
                r = self._rec("getActualTCPForce", ())
                return list(cell.wrench) if r is _NO else r

            def getTimestamp(self):
                r = self._rec("getTimestamp", ())
                return cell.stamp[self.arm] if r is _NO else r

            def getSafetyMode(self):
                r = self._rec("getSafetyMode", ())
                return cell.safety[self.arm] if r is _NO else r

            def getRobotStatus(self):
                r = self._rec("getRobotStatus", ())
                return cell.status[self.arm] if r is _NO else r

            def isConnected(self):
                r = self._rec("isConnected", ())
                return cell.connected[self.arm] if r is _NO else r

            def disconnect(self):
                self._rec("disconnect", ())

        self.RTDEControlInterface = Control
        self.RTDEReceiveInterface = Receive

    def clock(self):
        return self.t

    def tick(self):
        self.t += self.dt
        self.q = self.q + self.qd * self.dt
        for arm in (0, 1):
            if not self.frozen[arm]:
                self.stamp[arm] += self.dt

    def called(self, host, name, kind="control"):
        return [c[3] for c in self.calls if c[0] == host and c[1] == kind and c[2] == name]

    def host(self, arm):
        return [h for h, a in self.hosts.items() if a == arm][0]

    def stopped_both(self):
        """speedStop and stopScript reached both arms."""
        return all(self.called(self.host(a), "speedStop") and self.called(self.host(a), "stopScript")
                   for a in (0, 1))


class _NoValue:
    pass


_NO = _NoValue()
