//! Renders one seeded room scene (a torus as the object, two distractors, a support plane,
//! sensor noise) and writes the colour-mapped depth with the object mask overlaid.
//!
//! `cargo run -p ic_render --example debug_view -- out.png [seed]`

use std::sync::Arc;

use ic_render::*;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let out = args.next().unwrap_or_else(|| "debug_view.png".into());
    let seed: u64 = args.next().map(|s| s.parse()).transpose()?.unwrap_or(0);
    let object = Arc::new(ic_geometry::shapes::torus(0.75, 0.25, 100, 50).expect("valid torus"));
    let builder = SceneBuilder::new(SceneConfig {
        support_plane: Some(SupportPlaneConfig::default()),
        distractors: DistractorConfig {
            count: 2,
            size: (0.2, 0.5),
            ..Default::default()
        },
        ..SceneConfig::default()
    })?;
    let sample = builder.build(&object, seed)?;
    let mut renderer = default_renderer()?;
    let mut view = renderer.render(&sample.scene, &sample.camera)?;
    let sensor = SensorConfig {
        noise: Some(AxialNoise::default()),
        grazing: Some(GrazingDropout::default()),
        flying_pixels: Some(FlyingPixels::default()),
        quantisation: Some(Quantisation::Step { step: 0.001 }),
        ..SensorConfig::default()
    };
    sensor.apply(&mut view, seed);
    write_debug_png(&out, &view.depth, Some(&view.mask(OBJECT_ID)))?;
    let (obj, all) = view.count_returns(OBJECT_ID);
    println!("{}: {out}, object {obj} of {all} returns", renderer.name());
    Ok(())
}
