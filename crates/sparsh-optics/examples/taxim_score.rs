//! Temporary driver.
use sparsh_optics::CalibrationPack;
use sparsh_optics::sim2real::*;
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let pack = CalibrationPack::read(std::path::Path::new(&args[1])).unwrap();
    let setup = BallSetup {
        ball_radius_mm: 2.0,
        mm_per_px: args[2].parse().unwrap(),
    };
    let n = pack.frames.len();
    let even: Vec<usize> = (0..n).step_by(2).collect();
    let t = std::time::Instant::now();
    let cal = calibrate_pack(&pack, &even, setup, FitOptions::default()).unwrap();
    eprintln!("calib {:?}", t.elapsed());
    cal.save(std::path::Path::new(&args[3])).unwrap();
    let t = std::time::Instant::now();
    let scores: Vec<FrameScore> = (1..n)
        .step_by(2)
        .map(|k| render_and_score(&cal, &pack, k, setup).unwrap().1)
        .collect();
    eprintln!("score {:?}", t.elapsed());
    println!("{:#?}", summarize(&scores));
}
