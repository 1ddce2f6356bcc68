"""Study of issue #17 (not part of the library; studies/results/coverage_nuisance/).

Is the marginal posterior's linear nuisance map too narrow along one parameter?

usage: python studies/nuisance_profile.py CASE EFFECTS TARGET
(logs in runs/prof/data/CASE from coverage.cases(18) and gen.write_case; the fit
in runs/prof/CASE/fit from `jaxlift fit` on them, as the coverage study runs it)

Along the direction of TARGET's Laplace covariance column (the other sampled parameters at
their conditional optimum, quadratic drop 0.5 k^2 at k marginal sd), compare:
  marginal: make_log_prob of the marginal problem (nuisances on the linear map)
  conditional: nuisances held
  profile: the same whitened innovations with the nuisances (motor set not sampled,
           offsets) re-optimised by Gauss-Newton at each point (the true profile)
"""

import jax

jax.config.update("jax_enable_x64", True)
import json  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxlift as jl  # noqa: E402
from jaxlift.model.build import all_param_infos, make_effects, with_params  # noqa: E402
from jaxlift.model.params import from_unconstrained, to_unconstrained  # noqa: E402
from jaxlift.model.simulate import simulate  # noqa: E402
from jaxlift.posterior.problem import NOISE_NAMES, whitened_innovations  # noqa: E402

case, effects, target = sys.argv[1], [e for e in sys.argv[2].split(",") if e], sys.argv[3]
logs = [jl.read_log(f"runs/prof/data/{case}/{n}.csv") for n in ("fit_1", "fit_2")]
params = jl.load_params_json(f"runs/prof/{case}/fit/params.json", jl.all_param_infos("all"))
truth = json.load(open(f"runs/prof/data/{case}/truth.json"))["params"]
t0 = time.time()
probs = {
    c: jl.prepare_posterior(logs, effects=effects, params=params, conditioning=c)
    for c in ("marginal", "conditional")
}
print(f"prepared in {time.time() - t0:.0f} s", flush=True)
marg = probs["marginal"]
names = list(marg.names)
k = names.index(target)
cov = marg.cov_theta
sd = math.sqrt(cov[k, k])
print("sampled:", names, "nuisance:", marg.nuisance)
print("held nuisance directions:", marg.ls_info["nuisance_directions_held"])
for c, p in probs.items():
    print(f"{c}: Laplace sd of u({target}) = {math.sqrt(p.cov_theta[k, k]):.4g}")
tv = float(to_unconstrained(marg.infos[target], truth[target]))
print(
    f"fit u = {marg.theta_opt[k]:.5g}, truth u = {tv:.5g}, "
    f"(truth-fit)/sd = {(tv - marg.theta_opt[k]) / sd:.2f}"
)
ks = np.array([-2.0, -1.0, 0.0, 1.0, 2.0])
direction = cov[:, k] / cov[k, k] * sd  # one marginal sd of target, others conditional
thetas = marg.theta_opt[None] + ks[:, None] * direction[None]
quad = -0.5 * ks**2
out = {"ks": ks.tolist(), "quadratic": quad.tolist()}
for c, p in probs.items():
    lp = np.asarray(jl.make_log_prob(p, devices=1)(thetas))
    out[c] = (lp - lp[2]).tolist()
    print(f"{c:12s}", np.round(lp - lp[2], 3), "quadratic", quad, flush=True)

# the true profile: sampled coordinates fixed at thetas, the nuisances re-optimised
effs = make_effects(marg.effects)
infos_all = all_param_infos(effs)
phys = [j for j, n in enumerate(names) if n not in NOISE_NAMES]
motor = [n for n in marg.nuisance if not n.startswith("x0@")]
n_off = len(marg.experiments)
infos_th = [marg.infos[names[j]] for j in phys]
infos_m = [infos_all[m] for m in motor]
plant0, effs0 = marg.model.plant, marg.model.effects
rho, scale = jnp.asarray(marg.rho), jnp.asarray(marg.scale)


def innovations(phi, th):
    values = {info.name: from_unconstrained(info, th[j]) for j, info in enumerate(infos_th)}
    values.update({info.name: from_unconstrained(info, phi[j]) for j, info in enumerate(infos_m)})
    plant, es = with_params(plant0, effs0, values)
    exps = [
        eqx.tree_at(lambda e: e.inputs.x0, exp, exp.inputs.x0 + phi[len(motor) + i])
        for i, exp in enumerate(marg.experiments)
    ]
    sols = [simulate(plant, es, e.inputs, adjoint=diffrax.ForwardMode()) for e in exps]
    return whitened_innovations(exps, sols, rho, scale)


fe = jax.jit(innovations)
fj = jax.jit(jax.jacfwd(innovations))
phi0 = np.array(
    [float(to_unconstrained(infos_all[m], marg.values[m])) for m in motor] + [0.0] * n_off
)
a_map = np.asarray(marg.nuisance_map)


def half_ss(phi, th):
    e = np.asarray(fe(jnp.asarray(phi), jnp.asarray(th)))
    return 0.5 * float(e @ e)


jm0 = np.asarray(fj(jnp.asarray(phi0), jnp.asarray(marg.theta_opt[phys])))
col0 = np.linalg.norm(jm0, axis=0)
col0 = np.where(col0 > 0, col0, 1.0)
u0, sv0, vt0 = np.linalg.svd(jm0 / col0, full_matrices=False)
keep0 = sv0 > 1e-3 * sv0[0]
pinv0 = (vt0[keep0].T / sv0[keep0]) @ u0[:, keep0].T / col0[:, None]
chord = {1: [], 2: [], 3: []}
prof, lin = [], []
for i in range(len(ks)):
    th = thetas[i][phys]
    phi_lin = phi0 + a_map @ (th - marg.theta_opt[phys])
    lin.append(half_ss(phi_lin, th))
    phc = phi_lin.copy()
    for nst in (1, 2, 3):
        phc = phc - pinv0 @ np.asarray(fe(jnp.asarray(phc), jnp.asarray(th)))
        chord[nst].append(half_ss(phc, th))
    print("  chord steps:", [round(chord[n][-1], 3) for n in (1, 2, 3)], flush=True)
    phi = phi_lin.copy()
    f = lin[-1]
    for it in range(6):  # noqa: B007 (printed below)  # Gauss-Newton with a pseudo-inverse (rcond as the library's)
        e = np.asarray(fe(jnp.asarray(phi), jnp.asarray(th)))
        jm = np.asarray(fj(jnp.asarray(phi), jnp.asarray(th)))
        col = np.linalg.norm(jm, axis=0)
        col = np.where(col > 0, col, 1.0)
        step = -np.linalg.lstsq(jm / col, e, rcond=1e-3)[0] / col
        for lam in (1.0, 0.5, 0.25, 0.1):
            fn = half_ss(phi + lam * step, th)
            if fn < f:
                phi, f = phi + lam * step, fn
                break
        else:
            break
    prof.append(f)
    print(
        f"k={ks[i]:+.0f}: 0.5 ss linear map {lin[-1]:.3f}, profiled {f:.3f} ({it + 1} GN its)",
        flush=True,
    )
lin, prof = np.array(lin), np.array(prof)
out["linear_map_ll"] = (-(lin - lin[2])).tolist()
out["profile_ll"] = (-(prof - prof[2])).tolist()
print("likelihood only (priors left out):")
print("linear map ", np.round(-(lin - lin[2]), 3))
print("profile    ", np.round(-(prof - prof[2]), 3))
print("quadratic  ", quad)
for n in (1, 2, 3):
    c = np.array(chord[n])
    print(f"chord x{n}   ", np.round(-(c - c[2]), 3))
    out[f"chord{n}_ll"] = (-(c - c[2])).tolist()
json.dump(out, open(f"runs/prof/{case}_{target}_profile.json", "w"), indent=1)
print(f"total {time.time() - t0:.0f} s")
