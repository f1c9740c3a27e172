//! Element assembly four elements at a time, one element per vector lane
//! (AVX2 and FMA on x86-64; the scalar [`super::assemble_element`] elsewhere
//! and for the elements left over), and the node rotations of the warp the
//! same way ([`polar_rotations`]).
//!
//! The arithmetic is the scalar path's, lane by lane: the deformation
//! gradient, the rotation by the same scaled Newton iteration as
//! [`crate::math::polar_rotation_fast`], the co-rotated stress and the ten
//! stiffness blocks. Only the rounding differs (fused multiply–adds, another
//! order of the sums). An element whose determinant is not safely positive,
//! or whose iteration leaves the positive determinants or does not converge,
//! gets its rotation from the scalar [`crate::math::polar_rotation_near`], as
//! the scalar path would give it.

use super::{AssemblyInput, AssemblyOutput, Element};
use crate::math::Mat3;

/// Assembles the elements `0..4k` of `elements` (the largest multiple of
/// four) with [`super::RotationMethod::Polar`], exactly where the scalar
/// [`super::assemble_element`] puts them: element rotations into `elem_rot`,
/// forces and stiffness blocks into `out` (at the elements' `slots`).
/// Returns `4k`; the caller assembles the rest. Does nothing (returns 0)
/// where the CPU lacks AVX2 and FMA.
pub(crate) fn assemble_polar(
    elements: &[Element],
    slots: &[[usize; 16]],
    input: AssemblyInput<'_>,
    elem_rot: &mut [Mat3],
    out: &mut AssemblyOutput<'_>,
) -> usize {
    #[cfg(target_arch = "x86_64")]
    if crate::math::has_avx2_fma() {
        // SAFETY: the CPU supports the features the function is compiled for.
        return unsafe { imp::assemble_polar_avx2(elements, slots, input, elem_rot, out) };
    }
    let _ = (elements, slots, input, elem_rot, out);
    0
}

/// Replaces the matrices `m[0..4k]` (the largest multiple of four) by their
/// rotations, as [`crate::math::polar_rotation_fast`] gives them, four at a
/// time; returns `4k` (0 where the CPU lacks AVX2 and FMA). The caller
/// takes care of the rest.
pub(crate) fn polar_rotations(m: &mut [Mat3]) -> usize {
    #[cfg(target_arch = "x86_64")]
    if crate::math::has_avx2_fma() {
        // SAFETY: the CPU supports the features the function is compiled for.
        return unsafe { imp::polar_rotations_avx2(m) };
    }
    let _ = m;
    0
}

#[cfg(target_arch = "x86_64")]
mod imp {
    //! Every function here is compiled for AVX2 and FMA and inlined into
    //! [`assemble_polar_avx2`] and [`polar_rotations_avx2`] (a trait method
    //! cannot carry target features, so the lane arithmetic is written as
    //! inherent method calls, not operators: as operators the intrinsics
    //! were left as calls and the kernel ran slower than the scalar path).

    use std::arch::x86_64::*;

    use super::super::{AssemblyInput, AssemblyOutput, Element};
    use crate::math::{Mat3, Vec3};

    /// Four `f64`, one per element.
    #[derive(Clone, Copy)]
    struct L(__m256d);

    /// A lane-wise binary operation as an inherent method.
    macro_rules! binary {
        ($name:ident, $intrinsic:ident) => {
            #[inline]
            #[target_feature(enable = "avx2,fma")]
            fn $name(self, o: Self) -> Self {
                Self($intrinsic(self.0, o.0))
            }
        };
    }

    // Named like the operator traits on purpose; see the module docs.
    #[allow(clippy::should_implement_trait)]
    impl L {
        #[inline]
        #[target_feature(enable = "avx2,fma")]
        fn splat(v: f64) -> Self {
            Self(_mm256_set1_pd(v))
        }
        #[inline]
        #[target_feature(enable = "avx2,fma")]
        fn from_array(a: [f64; 4]) -> Self {
            Self(_mm256_set_pd(a[3], a[2], a[1], a[0]))
        }
        #[inline]
        #[target_feature(enable = "avx2,fma")]
        fn to_array(self) -> [f64; 4] {
            let mut a = [0.0; 4];
            // SAFETY: `a` holds four values.
            unsafe { _mm256_storeu_pd(a.as_mut_ptr(), self.0) };
            a
        }
        binary!(add, _mm256_add_pd);
        binary!(sub, _mm256_sub_pd);
        binary!(mul, _mm256_mul_pd);
        binary!(div, _mm256_div_pd);
        #[inline]
        #[target_feature(enable = "avx2,fma")]
        fn sqrt(self) -> Self {
            Self(_mm256_sqrt_pd(self.0))
        }
        /// `self · b + c` in each lane.
        #[inline]
        #[target_feature(enable = "avx2,fma")]
        fn fma(self, b: Self, c: Self) -> Self {
            Self(_mm256_fmadd_pd(self.0, b.0, c.0))
        }
    }

    /// A 3-vector of lanes.
    type V = [L; 3];
    /// A 3×3 matrix of lanes, `m[row][col]`.
    type M = [[L; 3]; 3];

    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn dot(a: &V, b: &V) -> L {
        a[2].fma(b[2], a[1].fma(b[1], a[0].mul(b[0])))
    }

    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn cross(a: &V, b: &V) -> V {
        [
            a[1].mul(b[2]).sub(a[2].mul(b[1])),
            a[2].mul(b[0]).sub(a[0].mul(b[2])),
            a[0].mul(b[1]).sub(a[1].mul(b[0])),
        ]
    }

    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn norm2(m: &M) -> L {
        let mut s = L::splat(0.0);
        for row in m {
            for &v in row {
                s = v.fma(v, s);
            }
        }
        s
    }

    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn col(m: &M, c: usize) -> V {
        [m[0][c], m[1][c], m[2][c]]
    }

    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn det(m: &M) -> L {
        dot(&col(m, 0), &cross(&col(m, 1), &col(m, 2)))
    }

    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn zero_m() -> M {
        let z = L::splat(0.0);
        [[z; 3]; 3]
    }

    /// `Σ_a p_a g_aᵀ` for four nodes.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn gradient(p: &[V; 4], g: &[V; 4]) -> M {
        let mut m = zero_m();
        for r in 0..3 {
            for c in 0..3 {
                let mut s = p[0][r].mul(g[0][c]);
                for a in 1..4 {
                    s = p[a][r].fma(g[a][c], s);
                }
                m[r][c] = s;
            }
        }
        m
    }

    /// `m v`.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn mul_mv(m: &M, v: &V) -> V {
        let mut out = [L::splat(0.0); 3];
        for r in 0..3 {
            out[r] = m[r][2].fma(v[2], m[r][1].fma(v[1], m[r][0].mul(v[0])));
        }
        out
    }

    /// The four lanes of `m` as matrices.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn extract(m: &M) -> [Mat3; 4] {
        let mut a = [[[0.0; 4]; 3]; 3];
        for r in 0..3 {
            for c in 0..3 {
                a[r][c] = m[r][c].to_array();
            }
        }
        let mut out = [Mat3::zeros(); 4];
        for (l, o) in out.iter_mut().enumerate() {
            for r in 0..3 {
                for c in 0..3 {
                    o[(r, c)] = a[r][c][l];
                }
            }
        }
        out
    }

    /// `m` with lane `l` set to `v`.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn set_lane(m: &mut M, l: usize, v: &Mat3) {
        for (i, row) in m.iter_mut().enumerate() {
            for (j, x) in row.iter_mut().enumerate() {
                let mut a = x.to_array();
                a[l] = v[(i, j)];
                *x = L::from_array(a);
            }
        }
    }

    /// Lanes `[p[i0][k], …, p[i3][k]]` for `k = 0, 1, 2`.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn gather(p: &[Vec3], i: [usize; 4]) -> V {
        let (a, b, c, d) = (&p[i[0]], &p[i[1]], &p[i[2]], &p[i[3]]);
        [
            L::from_array([a.x, b.x, c.x, d.x]),
            L::from_array([a.y, b.y, c.y, d.y]),
            L::from_array([a.z, b.z, c.z, d.z]),
        ]
    }

    /// See [`super::polar_rotations`].
    #[target_feature(enable = "avx2,fma")]
    pub(super) fn polar_rotations_avx2(m: &mut [Mat3]) -> usize {
        let groups = m.len() / 4;
        for gi in 0..groups {
            let q = &mut m[4 * gi..4 * gi + 4];
            let mut f = zero_m();
            for (i, row) in f.iter_mut().enumerate() {
                for (j, x) in row.iter_mut().enumerate() {
                    *x = L::from_array([q[0][(i, j)], q[1][(i, j)], q[2][(i, j)], q[3][(i, j)]]);
                }
            }
            let r = rotation(&f, |_, fl| crate::math::polar_rotation(fl));
            q.copy_from_slice(&extract(&r));
        }
        4 * groups
    }

    /// See [`super::assemble_polar`].
    #[target_feature(enable = "avx2,fma")]
    pub(super) fn assemble_polar_avx2(
        elements: &[Element],
        slots: &[[usize; 16]],
        input: AssemblyInput<'_>,
        elem_rot: &mut [Mat3],
        out: &mut AssemblyOutput<'_>,
    ) -> usize {
        let AssemblyInput { x, v, c_k, c_v } = input;
        let groups = elements.len() / 4;
        let (half, one, three) = (L::splat(0.5), L::splat(1.0), L::splat(3.0));
        let (cv, ck) = (L::splat(c_v), L::splat(c_k));
        for gi in 0..groups {
            let es = [
                &elements[4 * gi],
                &elements[4 * gi + 1],
                &elements[4 * gi + 2],
                &elements[4 * gi + 3],
            ];
            let mut xe = [[L::splat(0.0); 3]; 4];
            let mut ve = xe;
            let mut g = xe;
            for a in 0..4 {
                let nodes = [
                    es[0].nodes[a],
                    es[1].nodes[a],
                    es[2].nodes[a],
                    es[3].nodes[a],
                ];
                xe[a] = gather(x, nodes);
                ve[a] = gather(v, nodes);
                for k in 0..3 {
                    g[a][k] = L::from_array([
                        es[0].grads[a][k],
                        es[1].grads[a][k],
                        es[2].grads[a][k],
                        es[3].grads[a][k],
                    ]);
                }
            }
            let vol = L::from_array([es[0].volume, es[1].volume, es[2].volume, es[3].volume]);
            let lam = L::from_array([es[0].lambda, es[1].lambda, es[2].lambda, es[3].lambda]);
            let mu = L::from_array([es[0].mu, es[1].mu, es[2].mu, es[3].mu]);

            let f = gradient(&xe, &g);
            let prev = [
                &elem_rot[4 * gi],
                &elem_rot[4 * gi + 1],
                &elem_rot[4 * gi + 2],
                &elem_rot[4 * gi + 3],
            ];
            let r = rotation(&f, |l, fl| crate::math::polar_rotation_near(fl, prev[l]));
            for (l, rl) in extract(&r).into_iter().enumerate() {
                elem_rot[4 * gi + l] = rl;
            }
            // ft = F + c_v Fv; Rᵀ ft; ε = sym(Rᵀ ft − I); σ = λ tr ε I + 2μ ε.
            let fv = gradient(&ve, &g);
            let mut gu = zero_m();
            let mut ft = zero_m();
            for i in 0..3 {
                for j in 0..3 {
                    ft[i][j] = fv[i][j].fma(cv, f[i][j]);
                }
            }
            for i in 0..3 {
                for j in 0..3 {
                    gu[i][j] = r[2][i].fma(ft[2][j], r[1][i].fma(ft[1][j], r[0][i].mul(ft[0][j])));
                }
            }
            let tr = gu[0][0].add(gu[1][1]).add(gu[2][2]).sub(three);
            let two_mu = mu.add(mu);
            let mut sigma = zero_m();
            for i in 0..3 {
                for j in 0..3 {
                    sigma[i][j] = if i == j {
                        lam.fma(tr, two_mu.mul(gu[i][i].sub(one)))
                    } else {
                        two_mu.mul(gu[i][j].add(gu[j][i]).mul(half))
                    };
                }
            }
            // s = R σ V.
            let mut s = zero_m();
            for i in 0..3 {
                for j in 0..3 {
                    s[i][j] = r[i][2]
                        .fma(
                            sigma[2][j],
                            r[i][1].fma(sigma[1][j], r[i][0].mul(sigma[0][j])),
                        )
                        .mul(vol);
                }
            }
            let vl = vol.mul(lam).mul(ck);
            let vm = vol.mul(mu).mul(ck);
            let mut rg = [[L::splat(0.0); 3]; 4];
            for a in 0..4 {
                rg[a] = mul_mv(&r, &g[a]);
                let fa = mul_mv(&s, &g[a]);
                let fa = [fa[0].to_array(), fa[1].to_array(), fa[2].to_array()];
                for l in 0..4 {
                    out.rhs[es[l].nodes[a]] -= Vec3::new(fa[0][l], fa[1][l], fa[2][l]);
                }
            }
            for a in 0..4 {
                for b in a..4 {
                    let d = vm.mul(dot(&g[a], &g[b]));
                    let rbl = [rg[b][0].mul(vl), rg[b][1].mul(vl), rg[b][2].mul(vl)];
                    let ram = [rg[a][0].mul(vm), rg[a][1].mul(vm), rg[a][2].mul(vm)];
                    let mut blk = zero_m();
                    for i in 0..3 {
                        for j in 0..3 {
                            let o = rg[a][i].fma(rbl[j], rg[b][i].mul(ram[j]));
                            blk[i][j] = if i == j { o.add(d) } else { o };
                        }
                    }
                    for (l, kb) in extract(&blk).into_iter().enumerate() {
                        let sl = &slots[4 * gi + l];
                        if a == b {
                            out.values[sl[5 * a]] += kb;
                        } else {
                            out.values[sl[4 * a + b]] += kb;
                            out.values[sl[4 * b + a]] += kb.transpose();
                        }
                    }
                }
            }
        }
        4 * groups
    }

    /// The rotations of four deformation gradients by the scaled Newton
    /// iteration of [`crate::math::polar_rotation_fast`]; a lane `l` it does
    /// not suit gets `fallback(l, F_l)`.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn rotation(f: &M, fallback: impl Fn(usize, &Mat3) -> Mat3) -> M {
        let scale2 = norm2(f).to_array();
        let d0 = det(f).to_array();
        let mut ok = [false; 4];
        for l in 0..4 {
            ok[l] = crate::math::safely_positive(scale2[l], d0[l]);
        }
        let mut done = [false; 4];
        let mut xm = *f;
        if ok.iter().any(|&o| o) {
            // Lanes that are not `ok` iterate on the identity and are replaced below.
            let (mut d, mut x2) = (d0, scale2);
            for l in 0..4 {
                if !ok[l] {
                    set_lane(&mut xm, l, &Mat3::identity());
                    (d[l], x2[l]) = (1.0, 3.0);
                }
            }
            let (mut d, mut x2) = (L::from_array(d), L::from_array(x2));
            let half = L::splat(0.5);
            for _ in 0..12 {
                // Columns of the cofactor matrix: c_0 = x_1 × x_2, ...
                let (c0, c1, c2) = (col(&xm, 0), col(&xm, 1), col(&xm, 2));
                let cc = [cross(&c1, &c2), cross(&c2, &c0), cross(&c0, &c1)];
                let cn = dot(&cc[0], &cc[0])
                    .add(dot(&cc[1], &cc[1]))
                    .add(dot(&cc[2], &cc[2]));
                let gamma = cn.div(d.mul(d).mul(x2)).sqrt().sqrt();
                let a = gamma.mul(half);
                let b = half.div(gamma.mul(d));
                let mut next = zero_m();
                let mut delta2 = L::splat(0.0);
                for i in 0..3 {
                    for j in 0..3 {
                        next[i][j] = cc[j][i].fma(b, xm[i][j].mul(a));
                        let e = next[i][j].sub(xm[i][j]);
                        delta2 = e.fma(e, delta2);
                    }
                }
                xm = next;
                x2 = norm2(&xm);
                let (dl, xl) = (delta2.to_array(), x2.to_array());
                for l in 0..4 {
                    done[l] |= dl[l] <= 1e-16 * xl[l];
                }
                if done.iter().all(|&z| z) {
                    break;
                }
                let mut da = det(&xm).to_array();
                for l in 0..4 {
                    if !done[l] && (da[l].is_nan() || da[l] <= 0.0) {
                        ok[l] = false;
                        done[l] = true;
                    }
                    if !ok[l] {
                        // Keep the lane harmless for the iterations left.
                        da[l] = 1.0;
                    }
                }
                d = L::from_array(da);
            }
        }
        for l in 0..4 {
            if !(ok[l] && done[l]) {
                let fl = extract(f)[l];
                set_lane(&mut xm, l, &fallback(l, &fl));
            }
        }
        xm
    }
}

#[cfg(test)]
mod tests {
    use super::super::{
        AssemblyInput, AssemblyOutput, Element, RotationMethod, assemble_element,
        assembly::BlockPattern,
    };
    use crate::math::{Mat3, Vec3, polar_rotation_fast, test_value as val};
    use crate::mesh::generate;
    use nalgebra::Rotation3;

    /// Four at a time, the rotations are `polar_rotation_fast`'s to rounding:
    /// strained rotations, sums of nearby rotations (as the node rotations
    /// are), a flat, an inverted, a zero and a non-finite matrix, and a
    /// count that leaves a remainder for the caller.
    #[test]
    fn four_lanes_match_the_scalar_rotations() {
        let mut m: Vec<Mat3> = (0..41)
            .map(|k| {
                let r = Rotation3::from_euler_angles(val(k, 1), val(k, 2), val(k, 3));
                let s = Mat3::from_fn(|i, j| 0.3 * val(9 * k + 3 * i + j, 4) / 14.0);
                r.matrix() * (Mat3::identity() + s) * (1.0 + (k % 6) as f64)
            })
            .collect();
        let turn = *Rotation3::from_euler_angles(0.4, -1.2, 2.0).matrix();
        m[3] = turn * Mat3::from_diagonal(&Vec3::new(1.0, 0.7, 0.0));
        m[6] = turn * Mat3::from_diagonal(&Vec3::new(1.0, 1.2, -0.5));
        m[9] = Mat3::zeros();
        m[13] = Mat3::repeat(f64::NAN);
        let want: Vec<Mat3> = m.iter().map(polar_rotation_fast).collect();
        let done = super::polar_rotations(&mut m);
        if crate::math::has_avx2_fma() {
            assert_eq!(done, 40);
        }
        for r in &mut m[done..] {
            *r = polar_rotation_fast(r);
        }
        for (k, (a, b)) in m.iter().zip(&want).enumerate() {
            assert!(a.iter().all(|v| v.is_finite()), "matrix {k}: {a}");
            assert!((a - b).norm() <= 1e-12, "matrix {k}: {a} against {b}");
        }
    }

    /// The four-lane assembly gives the scalar path's rotations, forces and
    /// blocks to rounding, on a lens mesh turned, strained, with velocities
    /// and with some elements crushed flat or turned inside out (the lanes
    /// these take go to the SVD branch of `polar_rotation_near`, which needs
    /// the previous rotations, here arbitrary ones).
    #[test]
    fn four_lanes_match_the_scalar_assembly() {
        let mesh = generate::ellipsoid([4.75e-3, 4.75e-3, 2.25e-3], 5).expect("mesh");
        let rest = mesh.positions();
        let turn = Rotation3::from_euler_angles(0.3, -0.7, 1.1);
        let mut x: Vec<Vec3> = rest
            .iter()
            .enumerate()
            .map(|(i, p)| turn * p + Vec3::new(val(i, 1), val(i, 2), val(i, 3)) * 2e-6)
            .collect();
        // Crush the nodes of every seventh element onto a plane, and push one
        // node of every eleventh through the opposite face.
        let tets = mesh.tets();
        let mut crushed = 0;
        for (k, t) in tets.iter().enumerate() {
            if k % 7 == 0 {
                for &n in t {
                    x[n].z = x[t[0]].z;
                }
                crushed += 1;
            } else if k % 11 == 0 {
                let c = (x[t[1]] + x[t[2]] + x[t[3]]) / 3.0;
                x[t[0]] = c + (c - x[t[0]]) * 0.5;
                crushed += 1;
            }
        }
        let v: Vec<Vec3> = (0..x.len())
            .map(|i| Vec3::new(val(i, 4), val(i, 5), val(i, 6)) * 1e-3)
            .collect();
        let elements: Vec<Element> = tets
            .iter()
            .enumerate()
            .map(|(k, t)| {
                let (lam, mu) = (1e4 * (1.0 + (k % 5) as f64), 3e3 * (1.0 + (k % 3) as f64));
                Element::new(*t, t.map(|n| rest[n]), lam, mu)
            })
            .collect();
        let prev: Vec<Mat3> = (0..tets.len())
            .map(|k| *Rotation3::from_euler_angles(val(k, 7), val(k, 8), val(k, 9)).matrix())
            .collect();
        let pattern = BlockPattern::new(x.len(), tets);
        let (c_k, c_v) = (4e-4 + 1e-5, 0.02 + 0.5);

        let run = |lanes: bool| {
            let mut rot = prev.clone();
            let mut values = vec![Mat3::zeros(); pattern.nnz()];
            let mut rhs = vec![Vec3::zeros(); x.len()];
            let input = AssemblyInput {
                x: &x,
                v: &v,
                c_k,
                c_v,
            };
            let mut out = AssemblyOutput {
                values: &mut values,
                rhs: &mut rhs,
            };
            let slots = &pattern.element_slots;
            let first = if lanes {
                super::assemble_polar(&elements, slots, input, &mut rot, &mut out)
            } else {
                0
            };
            for ei in first..elements.len() {
                let e = &elements[ei];
                assemble_element(
                    e,
                    RotationMethod::Polar,
                    input,
                    &slots[ei],
                    &mut rot[ei],
                    &mut out,
                );
            }
            (first, rot, values, rhs)
        };
        let (first, rot_l, val_l, rhs_l) = run(true);
        let (_, rot_s, val_s, rhs_s) = run(false);
        if crate::math::has_avx2_fma() {
            assert_eq!(first, elements.len() / 4 * 4);
        } else {
            eprintln!("no AVX2/FMA: the lanes are not used on this CPU; scalar path only");
        }
        assert!(crushed > tets.len() / 10);
        let mut inverted = 0;
        for (k, (a, b)) in rot_l.iter().zip(&rot_s).enumerate() {
            assert!((a - b).norm() <= 1e-12, "element {k}: {a} against {b}");
            assert!((a.transpose() * a - Mat3::identity()).norm() <= 1e-12);
            let e = &elements[k];
            let f = e.deformation_gradient(&e.nodes.map(|n| x[n]));
            inverted += usize::from(f.determinant() <= 0.0);
        }
        assert!(inverted > 0, "no element took the SVD branch");
        let scale = val_s.iter().map(|m| m.norm()).fold(0.0, f64::max);
        for (a, b) in val_l.iter().zip(&val_s) {
            assert!((a - b).norm() <= 1e-12 * scale);
        }
        let scale = rhs_s.iter().map(|f| f.norm()).fold(0.0, f64::max);
        assert!(scale > 0.0);
        for (a, b) in rhs_l.iter().zip(&rhs_s) {
            assert!((a - b).norm() <= 1e-12 * scale);
        }
    }
}
