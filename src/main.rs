//! The `nerflabel` command line: parse, call the library, print.

fn main() {
    println!("nerflabel");
}
