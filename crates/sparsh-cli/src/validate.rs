//! `sparsh validate`: the contact solvers against analytic solutions (the cases of
//! `scenes/validation/`, see `sparsh_contact::validation`).

use std::path::Path;

use anyhow::Result;
use sparsh_contact::validation::{Report, run_cases};

/// Runs the cases of `dir`, prints the table (or JSON) and fails if a row misses its tolerance.
pub fn validate(dir: &Path, json: bool) -> Result<()> {
    let report = run_cases(dir)?;
    if json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print_table(&report);
    }
    let missed = report.rows.iter().filter(|r| !r.passed()).count();
    anyhow::ensure!(
        missed == 0,
        "{missed} of {} validation rows miss their tolerance",
        report.rows.len()
    );
    Ok(())
}

fn print_table(report: &Report) {
    println!(
        "{:<22} {:<22} {:>12} {:>12} {:>9} {:>6} {:>8}  result",
        "case", "quantity", "analytic", "simulated", "rel.err", "tol", "ms"
    );
    for r in &report.rows {
        println!(
            "{:<22} {:<22} {:>12.6} {:>12.6} {:>+8.3}% {:>6} {:>8.1}  {}",
            r.case,
            r.quantity,
            r.analytic,
            r.simulated,
            100.0 * r.rel_error,
            r.tolerance
                .map_or("report".into(), |t| format!("{:.0}%", 100.0 * t)),
            r.ms,
            match (r.tolerance, r.passed()) {
                (None, _) => "-",
                (Some(_), true) => "ok",
                (Some(_), false) => "MISS",
            }
        );
    }
    let reported = report.rows.iter().filter(|r| r.tolerance.is_none()).count();
    if reported > 0 {
        println!(
            "({reported} rows marked `report` are compared for information, not graded: lengths \
             measured from the contact mask, and references whose accuracy is not established)"
        );
    }
    if !report.convergence.is_empty() {
        println!(
            "\nconvergence under refinement (|rel. error| at each cell size, or finite elements per \
             contact radius; observed order)"
        );
        for c in &report.convergence {
            let errors: Vec<String> = c
                .cell_mm
                .iter()
                .zip(&c.rel_error)
                .map(|(h, e)| {
                    if c.case.ends_with("(elements per radius)") {
                        format!("{:.0} per radius: {:.2e}", 1.0 / h, e.abs())
                    } else {
                        format!("{h:.4} mm: {:.2e}", e.abs())
                    }
                })
                .collect();
            let orders: Vec<String> = c.observed_order.iter().map(|p| format!("{p:.2}")).collect();
            println!(
                "{:<22} {:<22} {}  order {}",
                c.case,
                c.quantity,
                errors.join(", "),
                orders.join(", ")
            );
        }
    }
}
