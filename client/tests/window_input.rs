//! The window's input path without a screen: mouse and keyboard events go through the
//! window's event handling (`viewer::Hands`), become tool commands, and drive the local
//! site of `cosurg run` (`LocalSite`): a drag and a wheel bring the forceps to the
//! gallbladder's fundus, the jaw key grasps it and an upward drag lifts it.

use cosurg::run_window::LocalSite;
use sim_core::SimOptions;
use sim_core::sim_scene::builtin;
use viewer::camera::WHEEL_DEPTH_STEP;
use viewer::three_d::{Event, Key, Modifiers, MouseButton, PhysicalPoint};
use viewer::{FrameBuilder, Hands, ToolCommand, ViewerCommand};

const HEIGHT_PX: f64 = 720.0;

fn feed(site: &mut LocalSite, builder: &mut FrameBuilder, hands: &mut Hands, events: &[Event]) {
    let frame = site.frame(builder, false, None);
    let mut out: Vec<ToolCommand> = Vec::new();
    for e in events {
        hands.handle(e, &frame, HEIGHT_PX, 1.0, &mut out);
    }
    for c in out {
        assert!(site.apply(ViewerCommand::Tool(c)).unwrap());
    }
}

fn run_for(site: &mut LocalSite, seconds: f64) {
    let dt = site.sim.options().dt;
    for _ in 0..(seconds / dt).round() as usize {
        site.step().unwrap();
    }
}

fn fundus(site: &LocalSite) -> nalgebra::Vector3<f64> {
    site.sim
        .probes()
        .into_iter()
        .find(|(n, _)| n == "fundus")
        .unwrap()
        .1
}

fn drag_px(dx: f64, dy: f64) -> Event {
    Event::MouseMotion {
        button: Some(MouseButton::Left),
        delta: (dx as f32, dy as f32),
        position: PhysicalPoint { x: 300.0, y: 300.0 },
        modifiers: Modifiers::default(),
        handled: false,
    }
}

#[test]
fn mouse_and_keyboard_grasp_and_lift_the_gallbladder() {
    let scene = builtin::cholecystectomy();
    let options = SimOptions::from_scene(&scene.scene);
    // where the canned script closes the jaws: the fundus
    let grasp_at = scene.scripts["forceps"]
        .sample("forceps", 2.0)
        .unwrap()
        .position;
    let mut site = LocalSite::new(scene, options, false).unwrap();
    let mut builder = FrameBuilder::new(&site.sim).unwrap();
    let mut hands = Hands::default();
    assert_eq!(site.active_tool(), "forceps");

    // 1. wheel to the fundus' depth, then drag across to it
    let frame = site.frame(&mut builder, false, None);
    let view = hands.view(&frame);
    let tip = frame.tools[0].pose.translation.vector;
    let notches = (view.depth_of(&grasp_at) - view.depth_of(&tip)) / WHEEL_DEPTH_STEP;
    let wheel = Event::MouseWheel {
        delta: (0.0, (notches * 24.0) as f32),
        position: PhysicalPoint { x: 300.0, y: 300.0 },
        modifiers: Modifiers::default(),
        handled: false,
    };
    feed(&mut site, &mut builder, &mut hands, &[wheel]);
    let pushed = hands.tool_target.unwrap();
    let d = grasp_at - pushed;
    let mpp = view.metres_per_pixel(view.depth_of(&pushed), HEIGHT_PX);
    let (dx, dy) = (d.dot(&view.right()) / mpp, -d.dot(&view.image_up()) / mpp);
    feed(&mut site, &mut builder, &mut hands, &[drag_px(dx, dy)]);
    assert!((hands.tool_target.unwrap() - grasp_at).norm() < 1e-4);
    run_for(&mut site, 0.5);
    let tip = site.interaction.tools.tools[0].tip();
    assert!(
        (tip - grasp_at).norm() < 2e-3,
        "the forceps reached {tip}, not {grasp_at}"
    );

    // 2. the jaw key closes the forceps on the fundus
    feed(
        &mut site,
        &mut builder,
        &mut hands,
        &[Event::KeyPress {
            kind: Key::Space,
            modifiers: Modifiers::default(),
            handled: false,
        }],
    );
    run_for(&mut site, 0.3);
    assert!(
        site.interaction.contact.is_grasping(0),
        "the forceps did not grasp"
    );
    let before = fundus(&site);

    // 3. drag 3 cm up the screen and hold
    let target = hands.tool_target.unwrap();
    let mpp = view.metres_per_pixel(view.depth_of(&target), HEIGHT_PX);
    feed(
        &mut site,
        &mut builder,
        &mut hands,
        &[drag_px(0.0, -0.03 / mpp)],
    );
    run_for(&mut site, 0.6);
    assert!(site.interaction.contact.is_grasping(0), "the grasp let go");
    let lifted = (fundus(&site) - before).dot(&view.image_up());
    assert!(
        lifted > 0.01,
        "the fundus rose {:.1} mm up the screen, expected more than 10",
        lifted * 1e3
    );
}
