//! Prints the validation table of `scenes/validation` (the `sparsh validate` cases).
fn main() {
    let dir = std::env::args()
        .nth(1)
        .unwrap_or("scenes/validation".into());
    let report = sparsh_contact::validation::run_cases(std::path::Path::new(&dir)).unwrap();
    for r in &report.rows {
        println!(
            "{:<24} {:<22} {:>12.6} {:>12.6} {:>+9.4}% {:>6} {:>8.1}ms {}",
            r.case,
            r.quantity,
            r.analytic,
            r.simulated,
            100.0 * r.rel_error,
            r.tolerance
                .map_or("-".into(), |t| format!("{:.0}%", 100.0 * t)),
            r.ms,
            if r.passed() { "ok" } else { "MISS" }
        );
    }
    for c in &report.convergence {
        println!(
            "{} {} h={:?} e={:?} order={:?}",
            c.case, c.quantity, c.cell_mm, c.rel_error, c.observed_order
        );
    }
}
