//! Parameter files as ground stations write them, for the VAS's start-up upload (003
//! §3.3.3, AP_Parameters): Mission Planner's `NAME,VALUE` (or `NAME VALUE`) lines and
//! QGroundControl's tab-separated `SYSID COMPID NAME VALUE TYPE` lines; `#` starts a comment.

use std::path::Path;

/// One parameter of a file: its name, value and the line it was on.
#[derive(Clone, Debug, PartialEq)]
pub struct ParamLine {
    /// The parameter's name (at most 16 characters, as MAVLink carries it).
    pub name: String,
    /// Its value.
    pub value: f32,
    /// Its line in the file, from 1.
    pub line: usize,
}

/// Reads and parses the parameter file at `path`.
///
/// # Errors
/// The file cannot be read, or a line is not a parameter (named with its line).
pub fn load(path: &Path) -> Result<Vec<ParamLine>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    parse(&text).map_err(|e| format!("{}:{e}", path.display()))
}

/// Parses a parameter file's text.
///
/// # Errors
/// `LINE: what is wrong` for the first line that is not a parameter.
pub fn parse(text: &str) -> Result<Vec<ParamLine>, String> {
    let mut out = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line = i + 1;
        let body = raw.split('#').next().unwrap_or_default().trim();
        if body.is_empty() {
            continue;
        }
        let fields: Vec<&str> = if body.contains('\t') {
            body.split('\t').map(str::trim).collect()
        } else if body.contains(',') {
            body.split(',').map(str::trim).collect()
        } else {
            body.split_whitespace().collect()
        };
        // QGroundControl: system, component, name, value, type.
        let (name, value) = match fields.as_slice() {
            [name, value] => (*name, *value),
            [_, _, name, value, _] => (*name, *value),
            _ => {
                return Err(format!(
                    "{line}: `{body}` is not NAME,VALUE (Mission Planner) or SYSID COMPID NAME VALUE TYPE (QGroundControl)"
                ))
            }
        };
        let valid_name = !name.is_empty()
            && name.len() <= 16
            && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
        if !valid_name {
            return Err(format!(
                "{line}: `{name}` is not a parameter name (letters, digits and '_', at most 16)"
            ));
        }
        let value: f32 = value
            .parse()
            .ok()
            .filter(|v: &f32| v.is_finite())
            .ok_or_else(|| format!("{line}: `{value}` is not a number ({name})"))?;
        out.push(ParamLine {
            name: name.to_owned(),
            value,
            line,
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mission_planner_and_qgroundcontrol_files_read_alike() {
        let mp = "# Mission Planner\nWP_SPEED,3.5\nCRUISE_SPEED 2\n\nFENCE_ENABLE,1  # on\n";
        let qgc = "# Onboard parameters\n1\t1\tWP_SPEED\t3.5\t9\n1\t1\tCRUISE_SPEED\t2\t9\n1\t1\tFENCE_ENABLE\t1\t2\n";
        let names = |ps: Vec<ParamLine>| -> Vec<(String, f32)> {
            ps.into_iter().map(|p| (p.name, p.value)).collect()
        };
        let want = vec![
            ("WP_SPEED".to_owned(), 3.5),
            ("CRUISE_SPEED".to_owned(), 2.0),
            ("FENCE_ENABLE".to_owned(), 1.0),
        ];
        assert_eq!(names(parse(mp).unwrap()), want);
        assert_eq!(names(parse(qgc).unwrap()), want);
        assert_eq!(parse(mp).unwrap()[2].line, 5);
    }

    #[test]
    fn a_line_that_is_no_parameter_is_named() {
        for (text, says) in [
            ("WP_SPEED,fast", "2: `fast` is not a number (WP_SPEED)"),
            ("A_NAME_LONGER_THAN_16,1", "is not a parameter name"),
            ("WP-SPEED,1", "is not a parameter name"),
            ("1,2,3", "is not NAME,VALUE"),
            ("WP_SPEED,NaN", "is not a number"),
        ] {
            let e = parse(&format!("# header\n{text}\n")).unwrap_err();
            assert!(e.contains(says), "{text}: {e}");
            assert!(e.starts_with("2: "), "{text}: {e}");
        }
    }
}
