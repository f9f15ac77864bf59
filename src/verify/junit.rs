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
        if !c.passed {
            xml += &format!("<failure message=\"{}\"/>", escape(&format!("{} = {} (required {relation} {})", c.name, c.value, c.threshold)));
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
        let checks = vec![Check::max("rel_l2 <det>", 0.5, 0.1), Check::min("cosine", 1.0, 0.99)];
        let xml = render("m&m", &checks, 1.0);
        assert!(xml.contains("tests=\"2\" failures=\"1\""));
        assert!(xml.contains("name=\"rel_l2 &lt;det&gt;\"><failure message=\"rel_l2 &lt;det&gt; = 0.5 (required &lt;= 0.1)\"/></testcase>"));
        assert!(xml.contains("name=\"cosine\"></testcase>"));
        assert!(xml.contains("testsuite name=\"m&amp;m\""));
    }
}
