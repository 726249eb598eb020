"""An independent simulator of the published Paderborn 4-node LPTN, for discovery's tests.

Written from the published equations (Wallscheid & Böcker 2016, parameters from Wallscheid's
2017 dissertation) with numpy and ``scipy.integrate.solve_ivp``; it shares no code with
:mod:`thermal_edge.lptn` (no model file, no law grammar, no discretisation), so that a test
of discovery on its data checks the workflow against physics written down a second time.

Hidden effects are added as extra terms of the right-hand side:

* ``bearing``: mechanical (bearing) loss ``p * |rpm| / 6000`` W into the rotor, which this model
  represents by the magnet node alone;
* ``none``: the published model as it is.

The loss map and the drag curve are the measured tables of ``../shared/data/paderborn``
(nearest look-up: RMS current to 2.5 A signed by torque, speed to 100 rpm).
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

C = np.array([1.0666e4, 6.5093e3, 0.437127e3, 3.5105e3])  # pm, sy, st, sw (J/K)
PM, SY, ST, SW = range(4)
R_DC = 14.6e-3


@dataclass(frozen=True)
class Tables:
    currents: np.ndarray  # signed RMS A
    speeds: np.ndarray  # rpm
    loss: np.ndarray  # W, [current, speed]
    drag: np.ndarray  # over ``speeds``

    @classmethod
    def read(cls, folder: Path) -> Tables:
        with open(folder / "loss_map_250V.csv", newline="") as f:
            rows = list(csv.reader(f))
        speeds = np.array([float(x) for x in rows[0][1:]])
        currents = np.array([float(r[0]) for r in rows[1:]])
        loss = np.array([[float(x) for x in r[1:]] for r in rows[1:]])
        with open(folder / "drag_curve.csv", newline="") as f:
            drows = list(csv.reader(f))[1:]
        d_rpm = np.array([float(r[0]) for r in drows])
        drag = np.interp(speeds, d_rpm, [float(r[1]) for r in drows])
        return cls(currents, speeds, loss, drag)

    def lookup(self, i_signed: float, rpm: float) -> tuple[float, float]:
        i = int(np.argmin(np.abs(self.currents - i_signed)))
        j = int(np.argmin(np.abs(self.speeds - abs(rpm))))
        return float(self.loss[i, j]), float(self.drag[j])


def derivative(T: np.ndarray, rpm: float, i_rms: float, torque: float, amb: float, cool: float, tables: Tables,
               bearing_w: float) -> np.ndarray:
    """dT/dt (K/s) of the four nodes at one operating point."""
    n = abs(rpm) / 6000.0
    c = cool / 100.0
    k_ac = 1 + 0.562 * n + 0.2407 * n**2
    p_dc = 3 * R_DC * i_rms**2
    p_cu_ref = p_dc * k_ac
    lam = 1 + 0.002 * (T[SW] - 70)
    p_sw = p_dc * lam + p_cu_ref * (k_ac - 1) / max(max(abs(lam), 1e-4) ** 2.5667, 1e-5)
    L, D = tables.lookup(i_rms * np.sign(torque), rpm)
    p_fe = L - 1.4762 * D - p_cu_ref
    k1 = min(max(0.5441 + 0.0078 * n + 0.0352 * (i_rms / 256) - 0.7438 * n * (i_rms / 256), 0.0), 1.0)
    P = np.array([
        (1 - k1) * p_fe * (1 - 0.0028 * (T[PM] - 63)) + bearing_w * n,
        0.8655 * k1 * p_fe * (1 - 0.0028 * (T[SY] - 55)),
        0.1345 * k1 * p_fe * (1 - 0.0028 * (T[ST] - 65)),
        p_sw,
    ])

    def spd(m: float, b: float, a: float) -> float:
        return m * np.exp(-n / b) + a

    g = {
        (SY, SW): 1 / 0.0375, (SY, ST): 1 / 0.0707, (SW, ST): 1 / 0.0899,
        (ST, PM): 1 / spd(1.7275, 0.1573, 0.3039), (SW, PM): 1 / spd(0.8486, 0.1428, 0.2319),
    }
    flow = P.copy()
    for (a, b), gab in g.items():
        q = gab * (T[a] - T[b])
        flow[a] -= q
        flow[b] += q
    flow[SY] += (cool - T[SY]) / (0.018 * (1 - 0.0054 * (cool - 20)))
    flow[PM] += (amb - T[PM]) / spd(0.6349, 0.1184, 0.1205)
    flow[PM] += (cool - T[PM]) / max(0.3528 - 0.2484 * n + 0.0276 * c + 0.3331 * n * c, 1e-6)
    return flow / C


def drive_profile(dt_s: float = 5.0, seed: int = 3) -> dict[str, np.ndarray]:
    """A varied drive: 40 segments of 6 min, speed and current drawn independently (so that
    a speed-driven loss and a current-driven one leave different marks), ambient 24 °C, coolant
    at 45 °C with a slow swing."""
    rng = np.random.default_rng(seed)
    seg_s, n_seg = 360.0, 40
    speeds = rng.choice([0.0, 1500.0, 3000.0, 4500.0, 6000.0], n_seg)
    currents = rng.choice([0.0, 40.0, 80.0, 120.0, 160.0], n_seg)
    t = np.arange(0.0, seg_s * n_seg, dt_s)
    k = np.minimum((t // seg_s).astype(int), n_seg - 1)
    return {
        "t": t, "speed_rpm": speeds[k], "i_rms": currents[k], "torque_nm": np.where(currents[k] > 0, 50.0, 0.0),
        "ambient_c": np.full(len(t), 24.0), "coolant_c": 45.0 + 5.0 * np.sin(2 * np.pi * t / 7200.0),
    }


def simulate(tables: Tables, inputs: dict[str, np.ndarray], bearing_w: float = 0.0, noise_k: float = 0.1,
             seed: int = 5) -> dict[str, np.ndarray]:
    """Sensor readings (°C) for the inputs (held over each sample), started at the coolant
    temperature; Gaussian noise of ``noise_k`` and 0.1 K quantisation, as a PT100 chain reads."""
    t = inputs["t"]
    T = np.full(4, float(inputs["coolant_c"][0]))
    out = np.empty((len(t), 4))
    out[0] = T
    for k in range(len(t) - 1):
        u = (inputs["speed_rpm"][k], inputs["i_rms"][k], inputs["torque_nm"][k], inputs["ambient_c"][k],
             inputs["coolant_c"][k])
        sol = solve_ivp(lambda _t, y, u=u: derivative(y, *u, tables, bearing_w), (t[k], t[k + 1]), T, method="LSODA",
                        rtol=1e-8, atol=1e-8)
        T = sol.y[:, -1]
        out[k + 1] = T
    rng = np.random.default_rng(seed)
    noisy = np.round((out + rng.normal(0.0, noise_k, out.shape)) * 10) / 10
    return {"pm": noisy[:, PM], "stator_yoke": noisy[:, SY], "stator_tooth": noisy[:, ST],
            "stator_winding": noisy[:, SW]}


def write_run(path: Path, inputs: dict[str, np.ndarray], sensors: dict[str, np.ndarray]) -> Path:
    """The run as a CSV the ``discover`` command reads (``t`` first, inputs, then sensors)."""
    cols = {**inputs, **sensors}
    names = list(cols)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(names)
        for k in range(len(inputs["t"])):
            w.writerow([f"{float(cols[n][k]):.6g}" for n in names])
    return path
