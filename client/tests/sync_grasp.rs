//! A receiver driven by the owner's keyframes follows a grasp-and-lift of the default
//! scene (in process, no network: frames are handed over directly).

use cosurg::site::Strategy;
use cosurg::site::glue::{Outgoing, SyncState, Tools};
use sim_core::sim_scene::builtin;
use sim_core::{SimOptions, Simulation};

#[test]
fn receiver_follows_grasp_and_lift() {
    follow(1);
}

#[test]
fn lagging_receiver_follows_grasp_and_lift() {
    follow(3);
}

/// The receiver steps once for every `lag`-th owner step until it falls 1.2 s behind,
/// then keeps pace: keyframes from its future wait for its clock.
fn follow(lag: usize) {
    let scene = builtin::cholecystectomy();
    let mut options = SimOptions::from_scene(&scene.scene);
    options.dt = 0.004;
    let mut owner = Simulation::new(scene.clone(), options.clone()).unwrap();
    let mut recv = Simulation::new(scene.clone(), options).unwrap();
    let mut tools = Tools::new(&owner, Some("forceps"), Strategy::Keyframe).unwrap();
    let mut s_owner = SyncState::new(&owner, Strategy::Keyframe);
    let mut s_recv = SyncState::new(&recv, Strategy::Keyframe);
    s_owner.set_sites(1, [1, 2]);
    s_recv.set_sites(2, [1, 2]);
    let script = scene.scripts.get("forceps").unwrap().clone();
    let mut owned = std::collections::BTreeSet::new();
    let mut worst: f64 = 0.0;
    let mut owner_frames: Vec<(f64, Vec<nalgebra::Vector3<f64>>)> = Vec::new();
    for k in 0..(7.0 / 0.004) as usize {
        let t = owner.time();
        let input = tools.local_input(Some(&script), t);
        let touched = tools.before_step(&mut owner, input, &s_owner).unwrap();
        for r in touched {
            if owned.insert(r) {
                s_owner.set_owner(r, Some(1), Some(1));
                s_recv.set_owner(r, Some(1), Some(2));
            }
        }
        s_owner.drive(&mut owner);
        owner.step().unwrap();
        for out in s_owner.outgoing(&owner) {
            match out {
                Outgoing::Keyframe(kf) => {
                    for (region, id) in s_recv.receive(&mut recv, kf) {
                        s_owner.on_ack(&proto::KeyframeAck {
                            region,
                            keyframe: id,
                            site: 2,
                        });
                    }
                }
                Outgoing::Delta(d) => {
                    eprintln!("delta region {} base {}", d.region, d.base_keyframe);
                    s_recv.receive_delta(&mut recv, d);
                }
            }
        }
        owner_frames.push((owner.time(), owner.surfaces()[0].deformed.clone()));
        if lag > 1 && k % lag != 0 && owner.time() - recv.time() < 1.2 {
            continue;
        }
        for (region, id) in s_recv.apply_due(&mut recv) {
            s_owner.on_ack(&proto::KeyframeAck {
                region,
                keyframe: id,
                site: 2,
            });
        }
        s_recv.drive(&mut recv);
        recv.step().unwrap();
        // Compare with the owner at the same simulated time.
        let Some((_, a)) = owner_frames
            .iter()
            .find(|(t, _)| (t - recv.time()).abs() < 1e-9)
        else {
            continue;
        };
        let b = &recv.surfaces()[0].deformed;
        let d = a
            .iter()
            .zip(b)
            .map(|(p, q)| (p - q).norm())
            .fold(0.0, f64::max);
        if d > worst + 0.002 {
            let i = a
                .iter()
                .zip(b)
                .enumerate()
                .max_by(|x, y| (x.1.0 - x.1.1).norm().total_cmp(&(y.1.0 - y.1.1).norm()))
                .unwrap()
                .0;
            let (host, w, nodes) = recv.surfaces()[0].embedding.host(i);
            eprintln!(
                "lag={lag} t={t:.3} d={d:.4} v={i} owner={:?} recv={:?} host={host:?} w={w:?} nodes={nodes:?} owned={owned:?}",
                a[i], b[i]
            );
        }
        worst = worst.max(d);
    }
    // Bounds: the release of the grasp (tissue springing back while the owner still owns
    // the region for 0.4 s) is the largest transient, ≈ 12 mm at 4 ms steps for a
    // receiver level with the owner (it extrapolates); a receiver behind the owner holds
    // the next keyframe and interpolates towards it (≈ 7.5 mm: the snap is faster than
    // the owner's 30 ms keyframe rate cap). At the end the tissue has settled on both.
    let bound = if lag > 1 { 0.010 } else { 0.015 };
    assert!(worst < bound, "receiver diverged by {worst} m");
    let a = &owner.surfaces()[0].deformed;
    let b = &recv.surfaces()[0].deformed;
    if (owner.time() - recv.time()).abs() < 1e-9 {
        let end = a
            .iter()
            .zip(b)
            .map(|(p, q)| (p - q).norm())
            .fold(0.0, f64::max);
        assert!(end < 0.001, "settled divergence {end} m");
    }
}
