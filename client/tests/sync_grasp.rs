//! A receiver driven by the owner's keyframes follows a grasp-and-lift of the default
//! scene (in process, no network: frames are handed over directly).

use cosurg::site::Strategy;
use cosurg::site::glue::{Outgoing, SyncState, Tools};
use sim_core::sim_scene::builtin;
use sim_core::{SimOptions, Simulation};

#[test]
fn receiver_follows_grasp_and_lift() {
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
    for _ in 0..(4.5 / 0.004) as usize {
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
        s_recv.apply_due(&mut recv);
        s_recv.drive(&mut recv);
        recv.step().unwrap();
        let a = &owner.surfaces()[0].deformed;
        let b = &recv.surfaces()[0].deformed;
        let d = a
            .iter()
            .zip(b)
            .map(|(p, q)| (p - q).norm())
            .fold(0.0, f64::max);
        if d > worst + 0.005 {
            let i = a
                .iter()
                .zip(b)
                .enumerate()
                .max_by(|x, y| (x.1.0 - x.1.1).norm().total_cmp(&(y.1.0 - y.1.1).norm()))
                .unwrap()
                .0;
            let (host, w, nodes) = recv.surfaces()[0].embedding.host(i);
            eprintln!(
                "t={t:.3} d={d:.4} v={i} owner={:?} recv={:?} host={host:?} w={w:?} nodes={nodes:?} owned={owned:?}",
                a[i], b[i]
            );
        }
        worst = worst.max(d);
    }
    assert!(worst < 0.005, "receiver diverged by {worst} m");
}
