fn main() {
    let mut n = choreo_models::NoiseSource::new(1, 0);
    let mut buf = vec![0f32; 1_000_000];
    let t = std::time::Instant::now();
    n.fill(&mut buf);
    println!("1M normals: {:.1} ms", t.elapsed().as_secs_f64() * 1e3);
}
