//! JUnit XML for CI systems that render test reports: one testsuite per verify run, one
//! testcase per gate check (a failure element when it did not hold).

use super::gate::Check;

/// The report as JUnit XML; `suite` names the candidate.
pub fn render(suite: &str, checks: &[Check], seconds: f64) -> String {
    let failures = checks.iter().filter(|c| !c.passed).count();
    let mut xml = String::from("<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n");
    xml += &format!("<testsuites tests=\"{}\" failures=\"{failures}\">\n", checks.len());
    xml += &format!("  <testsuite name=\"{}\" tests=\"{}\" failures=\"{failures}\" time=\"{seconds:.3}\">\n", escape(suite), checks.len());
    for c in checks {
        let relation = if c.kind == "max" { "<=" } else { ">=" };
        xml += &format!("    <testcase classname=\"pdi-compile.verify\" name=\"{}\">", escape(&c.name));
        match (c.value, &c.unmeasured) {
            (Some(v), _) if !c.passed => xml += &format!("<failure message=\"{}\"/>", escape(&format!("{} = {v} (required {relation} {})", c.name, c.threshold))),
            (None, Some(why)) if c.allowed => xml += &format!("<skipped message=\"{}\"/>", escape(&format!("not measured ({why}); allowed by --allow-unmeasured {}", c.key))),
            (None, why) => xml += &format!("<failure message=\"{}\"/>", escape(&format!("not measured: {}", why.as_deref().unwrap_or("no value")))),
            _ => {}
        }
        xml += "</testcase>\n";
    }
    xml += "  </testsuite>\n</testsuites>\n";
    xml
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;").replace('\'', "&apos;")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn failures_are_elements_and_names_are_escaped() {
        let checks = vec![Check::max("max_rel_l2", "rel_l2 <det>", 0.5, 0.1), Check::min("min_cosine", "cosine", 1.0, 0.99)];
        let xml = render("m&m", &checks, 1.0);
        assert!(xml.contains("tests=\"2\" failures=\"1\""));
        assert!(xml.contains("name=\"rel_l2 &lt;det&gt;\"><failure message=\"rel_l2 &lt;det&gt; = 0.5 (required &lt;= 0.1)\"/></testcase>"));
        assert!(xml.contains("name=\"cosine\"></testcase>"));
        assert!(xml.contains("testsuite name=\"m&amp;m\""));
    }

    #[test]
    fn an_unmeasured_check_fails_with_its_reason_unless_allowed() {
        let mut checks = vec![Check::unmeasured("max_map_drop", "drop", "max", 0.01, "no labels")];
        let xml = render("m", &checks, 1.0);
        assert!(xml.contains("failures=\"1\"") && xml.contains("<failure message=\"not measured: no labels\"/>"), "{xml}");
        crate::verify::gate::allow_unmeasured(&mut checks, &["max_map_drop".into()], crate::verify::gate::KEYS).unwrap();
        let xml = render("m", &checks, 1.0);
        assert!(xml.contains("failures=\"0\"") && xml.contains("<skipped message=\"not measured (no labels); allowed by --allow-unmeasured max_map_drop\"/>"), "{xml}");
        assert!(crate::verify::gate::allow_unmeasured(&mut checks, &["max_map_dorp".into()], crate::verify::gate::KEYS).is_err());
    }
}
