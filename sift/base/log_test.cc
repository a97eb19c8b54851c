#include "sift/base/log.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <cstdio>
#include <fstream>
#include <iterator>
#include <limits>
#include <regex>
#include <string>
#include <utility>
#include <vector>

namespace oxbow::log {
namespace {

using namespace std::string_literals;

TEST(JsonStringTest, QuotesAndEscapes) {
  EXPECT_EQ(JsonString(""), R"("")");
  EXPECT_EQ(JsonString("plain /v1/search"), R"("plain /v1/search")");
  EXPECT_EQ(JsonString(R"(say "hi" \ bye)"), R"("say \"hi\" \\ bye")");
  EXPECT_EQ(JsonString("a\nb\rc\td"), R"("a\nb\rc\td")");
  EXPECT_EQ(JsonString("\x01\x1f\x7f"), R"("\u0001\u001f\u007f")");
  EXPECT_EQ(JsonString("nul\0byte"s), R"("nul\u0000byte")");
}

TEST(JsonStringTest, KeepsWellFormedUtf8) {
  // 2, 3 and 4 byte sequences, the highest code point, and the last ones before the surrogates.
  const std::string text = "caf\xc3\xa9 \xe2\x82\xac \xf0\x9f\x98\x80 \xf4\x8f\xbf\xbf \xed\x9f\xbf";
  EXPECT_EQ(JsonString(text), "\"" + text + "\"");
}

TEST(JsonStringTest, ReplacesEveryByteThatIsNotUtf8) {
  EXPECT_EQ(JsonString("/v1/images/\xff\xfe"), R"("/v1/images/\ufffd\ufffd")");
  EXPECT_EQ(JsonString("cut \xe2\x82"), R"("cut \ufffd\ufffd")");                // truncated sequence
  EXPECT_EQ(JsonString("\xc0\xaf"), R"("\ufffd\ufffd")");                          // overlong '/'
  EXPECT_EQ(JsonString("\xed\xa0\x80"), R"("\ufffd\ufffd\ufffd")");                // surrogate U+D800
  EXPECT_EQ(JsonString("\xf4\x90\x80\x80"), R"("\ufffd\ufffd\ufffd\ufffd")");      // above U+10FFFF
  EXPECT_EQ(JsonString("\x80x"), R"("\ufffdx")");                                  // lone continuation byte
  EXPECT_EQ(JsonString("\xe2\x82\""), R"("\ufffd\ufffd\"")");                      // a quote never hides in a sequence
}

TEST(Utf8Test, WellFormedTextIsKeptAndEveryOtherByteReplaced) {
  const std::string text = "caf\xc3\xa9 \xe2\x82\xac \xf0\x9f\x98\x80 \xf4\x8f\xbf\xbf \xed\x9f\xbf";
  EXPECT_TRUE(IsWellFormedUtf8(text));
  EXPECT_TRUE(IsWellFormedUtf8(""));
  EXPECT_EQ(ToWellFormedUtf8(text), text);
  // U+FFFD is EF BF BD.
  for (const auto& [bad, good] : std::vector<std::pair<std::string, std::string>>{
           {"caf\xe9.png", "caf\xef\xbf\xbd.png"},                                        // Latin-1
           {"cut \xe2\x82", "cut \xef\xbf\xbd\xef\xbf\xbd"},                             // truncated sequence
           {"\xc0\xaf", "\xef\xbf\xbd\xef\xbf\xbd"},                                      // overlong '/'
           {"\xed\xa0\x80", "\xef\xbf\xbd\xef\xbf\xbd\xef\xbf\xbd"},                    // surrogate U+D800
           {"\x80x", "\xef\xbf\xbdx"}}) {                                                   // lone continuation byte
    EXPECT_FALSE(IsWellFormedUtf8(bad)) << bad;
    EXPECT_EQ(ToWellFormedUtf8(bad), good) << bad;
    EXPECT_TRUE(IsWellFormedUtf8(ToWellFormedUtf8(bad))) << bad;
  }
}

TEST(FormatTest, ParsesTheTwoNames) {
  Format format = Format::kText;
  EXPECT_TRUE(ParseFormat("json", &format));
  EXPECT_EQ(format, Format::kJson);
  EXPECT_TRUE(ParseFormat("text", &format));
  EXPECT_EQ(format, Format::kText);
  EXPECT_FALSE(ParseFormat("JSON", &format));
  EXPECT_FALSE(ParseFormat("", &format));
}

// Runs `write` with stderr sent to a file and the given format; returns what was written.
template <typename F>
std::string CaptureStderr(Format format, F write) {
  char path[] = "/tmp/oxbow_log_test_XXXXXX";
  const int fd = mkstemp(path);
  EXPECT_GE(fd, 0);
  std::fflush(stderr);
  const int saved = dup(STDERR_FILENO);
  dup2(fd, STDERR_FILENO);
  const Format saved_format = GetFormat();
  SetFormat(format);
  write();
  SetFormat(saved_format);
  std::fflush(stderr);
  dup2(saved, STDERR_FILENO);
  close(saved);
  close(fd);
  std::ifstream in(path, std::ios::binary);
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  unlink(path);
  return text;
}

TEST(LineTest, JsonLineHasTimeLevelMessageAndFieldsInOrder) {
  const std::vector<std::pair<const char*, double>> stages = {{"extract", 12.25}, {"quantize", 0.5}};
  const std::string text = CaptureStderr(Format::kJson, [&] {
    Line(Level::kWarning).Field("request_id", "abc").Field("status", 404).Field("latency_ms", 1.5)
            .Field("stages_ms", stages).Field("path", "/v1/images/\"\xff\n")
        << "http abc GET " << 7;
  });
  const std::regex expected(
      R"(\{"time":"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z","level":"warning","message":"http abc GET 7",)"
      R"("request_id":"abc","status":404,"latency_ms":1\.5,"stages_ms":\{"extract":12\.25,"quantize":0\.5\},)"
      R"("path":"/v1/images/\\"\\ufffd\\n"\}\n)");
  EXPECT_TRUE(std::regex_match(text, expected)) << text;
}

TEST(LineTest, JsonNumbersAreNeverNanOrInfinity) {
  const std::vector<std::pair<const char*, double>> stages = {{"a", std::numeric_limits<double>::quiet_NaN()}};
  const std::string text = CaptureStderr(Format::kJson, [&] {
    Line(Level::kInfo).Field("x", std::numeric_limits<double>::infinity()).Field("s", stages) << "m";
  });
  EXPECT_NE(text.find(R"("x":null,"s":{"a":null}})"), std::string::npos) << text;
}

TEST(LineTest, MessageIsEscapedAndEveryLevelHasItsName) {
  const std::string text = CaptureStderr(Format::kJson, [] {
    Line(Level::kDebug) << "a\tb";
    Line(Level::kInfo) << "quote \" here";
    Line(Level::kError) << "bad \xc3";
  });
  EXPECT_NE(text.find(R"("level":"debug","message":"a\tb"})"), std::string::npos) << text;
  EXPECT_NE(text.find(R"("level":"info","message":"quote \" here"})"), std::string::npos) << text;
  EXPECT_NE(text.find(R"("level":"error","message":"bad \ufffd"})"), std::string::npos) << text;
}

TEST(LineTest, TextFormatShowsOnlyTheMessage) {
  const std::string text = CaptureStderr(Format::kText, [] {
    Line(Level::kInfo).Field("status", 200).Field("route", "/v1/stats") << "http x GET /v1/stats";
  });
  EXPECT_TRUE(std::regex_match(text, std::regex(R"(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ I http x GET /v1/stats\n)")))
      << text;
}

TEST(LineTest, TextFormatEscapesControlCharacters) {
  // A client's bytes in a message (a path, a folder name) cannot end the line or forge the next one.
  const std::string text = CaptureStderr(Format::kText, [] {
    Line(Level::kInfo) << "backed up to /b\n2026-01-01T00:00:00Z I forged\r\t\x01" << "nul\0\x7f"s << " caf\xc3\xa9";
  });
  EXPECT_TRUE(std::regex_match(text, std::regex(R"(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ I backed up to /b\\n2026-01-01T00:00:00Z I )"
                                                R"(forged\\r\\t\\x01nul\\x00\\x7f caf\xc3\xa9\n)")))
      << text;
  EXPECT_EQ(TextSafe("plain /v1/search \"q\" \\"), "plain /v1/search \"q\" \\");
}

TEST(ProgressTest, JsonFormatWritesOneObjectPerDraw) {
  const std::string text = CaptureStderr(Format::kJson, [] {
    Progress progress("indexing \"x\"", 4, "images");
    progress.Advance(4);
  });
  EXPECT_TRUE(std::regex_match(text, std::regex(R"(\{"time":"[^"]+","level":"info","message":"indexing \\"x\\" \[#+\] 4/4 images[^\n]*"\}\n)")))
      << text;
}

}  // namespace
}  // namespace oxbow::log
